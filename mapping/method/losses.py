"""The four EMIE-MAP losses: masked L1 colour, masked cross-entropy semantics, L1 to Lidar ground
elevations, and the neighbour smoothness of the elevation."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def colour_l1(rendered: torch.Tensor, observed: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """1/|M| sum M |C - C_gt| over pixels (P, 3) in [0, 1], averaged over the three channels."""
    m = mask.to(rendered.dtype)[:, None]
    return (m * (rendered - observed).abs()).sum() / (3 * m.sum()).clamp(min=1)


def semantic_ce(logits: torch.Tensor, labels: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """1/|M| sum M CE(S, S_gt) on rendered logits (P, C) (log-softmax applied once, here)."""
    ce = F.cross_entropy(logits, labels.clamp(max=logits.shape[1] - 1), reduction="none")
    m = mask.to(ce.dtype)
    return (m * ce).sum() / m.sum().clamp(min=1)


def elevation_l1(z: torch.Tensor, z_lidar: torch.Tensor) -> torch.Tensor:
    """Mean |z - z_gt| over vertices that have Lidar ground points nearby."""
    if len(z) == 0:
        return z.new_zeros(())
    return (z - z_lidar).abs().mean()


def smoothness(z: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """sum_i sum_{j in N(i)} (z_i - z_j)^2, divided by the number of vertices (the paper's double sum
    taken per vertex so the weight does not grow with the window); edges (E, 2) index into z, each
    undirected edge once."""
    if len(edges) == 0:
        return z.new_zeros(())
    d = z[edges[:, 0]] - z[edges[:, 1]]
    return 2.0 * (d * d).sum() / len(z)
