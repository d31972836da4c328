"""Per-vertex colour parameters and their decoders: the paper's bank of per-camera MLPs and two ablations.

- "mlps" (EMIE-MAP): a shared 32-d code per vertex, one small MLP per camera (32->16->3, sigmoid).
- "embedding": one MLP fed the code plus a learned per-camera embedding.
- "explicit" (RoMe and the no-colour-MLPs ablation): three numbers per vertex through a sigmoid, the same
  colour for every camera.
"""

from __future__ import annotations

import torch
from torch import nn

CAMERA_EMBEDDING_DIM = 8


def colour_mlp(in_dim: int, layers: int, width: int) -> nn.Sequential:
    dims = [in_dim] + [width] * (layers - 1)
    blocks: list[nn.Module] = []
    for d_in, d_out in zip(dims[:-1], dims[1:], strict=True):
        blocks += [nn.Linear(d_in, d_out), nn.ReLU()]
    return nn.Sequential(*blocks, nn.Linear(dims[-1], 3), nn.Sigmoid())


class ColourDecoder(nn.Module):
    """decode(vertex colour parameters (M, D), camera name) -> RGB in [0, 1], (M, 3)."""

    def __init__(self, kind: str, camera_names: list[str], code_dim: int, layers: int = 2, width: int = 16):
        super().__init__()
        if kind not in ("mlps", "embedding", "explicit"):
            raise ValueError(f"unknown colour model {kind!r}")
        self.kind = kind
        self.camera_names = list(camera_names)
        self.code_dim = 3 if kind == "explicit" else code_dim
        if kind == "mlps":
            self.mlps = nn.ModuleDict({n: colour_mlp(code_dim, layers, width) for n in camera_names})
        elif kind == "embedding":
            self.embeddings = nn.Parameter(torch.randn(len(camera_names), CAMERA_EMBEDDING_DIM) * 0.1)
            self.mlp = colour_mlp(code_dim + CAMERA_EMBEDDING_DIM, layers, width)

    def decode(self, params: torch.Tensor, camera: str) -> torch.Tensor:
        if self.kind == "explicit":
            return torch.sigmoid(params)
        if self.kind == "mlps":
            return self.mlps[camera](params)
        e = self.embeddings[self.camera_names.index(camera)]
        return self.mlp(torch.cat([params, e.expand(len(params), -1)], 1))
