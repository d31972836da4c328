"""The elevation residual network: sin/cos positional encoding of (x, y) in metres and an 8x128 ReLU MLP.

The encoding is taken relative to a fixed origin with a fixed scale in metres (by default the length of
one optimisation window, 160 m), never normalised over the whole route, so a place keeps its encoding and
its frequency content however long the drive is. `residual` can evaluate the MLP on a coarse square
lattice and interpolate bilinearly (the residual is low-frequency by design), which is ~60x cheaper than
evaluating it at every 0.1 m vertex.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

_KEY_OFFSET = 1 << 20  # lattice indices within +-2^20 cells (+-524 km at 0.5 m)
_KEY_BASE = 1 << 21


def positional_encoding(p: torch.Tensor, dim: int) -> torch.Tensor:
    """(M, 2) scaled coordinates -> (M, dim): p itself then sin/cos(2^k pi p) for k < (dim - 2) / 4."""
    n_freq = (dim - 2) // 4
    freqs = (2.0 ** torch.arange(n_freq, dtype=p.dtype, device=p.device)) * torch.pi
    angles = (p[:, None, :] * freqs[None, :, None]).reshape(len(p), -1)
    enc = torch.cat([p, torch.sin(angles), torch.cos(angles)], 1)
    if enc.shape[1] < dim:  # odd remainders are padded with zeros so the width is what was asked for
        enc = torch.cat([enc, enc.new_zeros(len(p), dim - enc.shape[1])], 1)
    return enc


class ElevationMLP(nn.Module):
    """z_r = MLP(PE(x, y)); the last layer starts at zero so the surface starts at z0."""

    def __init__(
        self,
        origin_xy: tuple[float, float],
        encoding_dim: int = 22,
        layers: int = 8,
        width: int = 128,
        scale_m: float = 160.0,
    ):
        super().__init__()
        self.origin_xy = (float(origin_xy[0]), float(origin_xy[1]))
        self.scale_m = float(scale_m)
        self.encoding_dim = encoding_dim
        dims = [encoding_dim] + [width] * (layers - 1)
        blocks: list[nn.Module] = []
        for d_in, d_out in zip(dims[:-1], dims[1:], strict=True):
            blocks += [nn.Linear(d_in, d_out), nn.ReLU()]
        last = nn.Linear(dims[-1], 1)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.net = nn.Sequential(*blocks, last)

    def forward(self, xy_local_m: torch.Tensor) -> torch.Tensor:
        """Residual (M,) at (M, 2) coordinates in metres relative to origin_xy."""
        return self.net(positional_encoding(xy_local_m / self.scale_m, self.encoding_dim))[:, 0]

    def local(self, xy_world: np.ndarray) -> torch.Tensor:
        return torch.from_numpy((xy_world - np.asarray(self.origin_xy)).astype(np.float32))

    def residual(self, xy_world: np.ndarray, lattice_m: float = 0.0) -> torch.Tensor:
        """Residual at world points; lattice_m > 0 evaluates only the lattice nodes around them."""
        return self.residual_at(self.local(xy_world), lattice_m)

    def residual_at(self, p: torch.Tensor, lattice_m: float = 0.0) -> torch.Tensor:
        """`residual` at (M, 2) float32 points relative to origin_xy (a tensor on the MLP's device)."""
        if lattice_m <= 0:
            return self(p)
        g = p / lattice_m
        base = torch.floor(g)
        f = g - base
        base = base.to(torch.int64)
        step = torch.tensor([[1, 0], [0, 1], [1, 1]], device=base.device)
        corners = torch.stack([base, base + step[0], base + step[1], base + step[2]], 1)  # (M, 4, 2)
        key = (corners[..., 0] + _KEY_OFFSET) * _KEY_BASE + (corners[..., 1] + _KEY_OFFSET)
        unique_key, inverse = torch.unique(key.reshape(-1), return_inverse=True)
        nodes = torch.stack([unique_key // _KEY_BASE, unique_key % _KEY_BASE], 1) - _KEY_OFFSET
        values = self(nodes.to(torch.float32) * lattice_m)[inverse].reshape(-1, 4)
        fx, fy = f[:, 0], f[:, 1]
        w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
        return (values * w).sum(1)
