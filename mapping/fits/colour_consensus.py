"""The colour of a vertex from views without semantics: the consensus of its views instead of their mean.

Something standing above the road (a car, a cyclist, a bollard, a wall) covers, in each view, the ground behind it
along the camera's rays: radially away from that camera, so on different ground from each view. A ground vertex's
views then split into those that see the ground (and agree) and those that see one thing or another standing in
front of it (and agree neither with the ground nor with each other). The mean of them all is a smear; this takes,
per vertex and camera, the view whose brightness is the weighted median of its views (the nearer a view, the more
it weighs: its ray is steeper, so less of what stands nearer the camera can cover the vertex, and its pixel is
sharper), and averages the views within `tolerance` (mean absolute RGB, [0, 1]) of that view's colour. The result
is a colour one of the views showed, not a blend of the ground and what stood on it, so it keeps the images'
saturation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LUMA = np.array([0.299, 0.587, 0.114], np.float32)


@dataclass
class ColourReads:
    """Every colour read of the views without semantics, in chunks (one per view): the vertices (int32), the
    camera (its index), the colours (RGB in [0, 1], float16) and the view's weights at the vertices (float16):
    10 bytes a read."""

    vertex: list[np.ndarray] = field(default_factory=list)
    camera: list[int] = field(default_factory=list)
    colour: list[np.ndarray] = field(default_factory=list)
    weight: list[np.ndarray] = field(default_factory=list)

    def append(self, vertex: np.ndarray, camera: int, colour: np.ndarray, weight: np.ndarray) -> None:
        self.vertex.append(vertex.astype(np.int32))
        self.camera.append(int(camera))
        self.colour.append(colour.astype(np.float16))
        self.weight.append(weight.astype(np.float16))

    def extend(self, other: ColourReads) -> None:
        for mine, theirs in ((self.vertex, other.vertex), (self.camera, other.camera), (self.colour, other.colour),
                             (self.weight, other.weight)):
            mine.extend(theirs)

    def __len__(self) -> int:
        return sum(len(v) for v in self.vertex)


def proximity_weight(distance_m: np.ndarray, near_m: float) -> np.ndarray:
    """A view's weight at a point `distance_m` from its camera: 1 / (1 + (distance / near_m)^2)."""
    return 1.0 / (1.0 + (distance_m / near_m) ** 2)


@dataclass(frozen=True)
class Consensus:
    """Per (vertex, camera) pair with reads: its key (vertex * cameras + camera), the consensus colour, how many
    views agreed with it (the inliers) and how many were read."""

    key: np.ndarray  # (K,) int64, sorted
    colour: np.ndarray  # (K, 3) float32
    inliers: np.ndarray  # (K,) int64
    reads: np.ndarray  # (K,) int64


def consensus(reads: ColourReads, cameras: int, tolerance: float) -> Consensus:
    """The consensus colour of every (vertex, camera) pair in `reads` (the module's docstring)."""
    if not len(reads):
        return Consensus(np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                         np.zeros(0, np.int64))
    key = (np.concatenate(reads.vertex).astype(np.int64) * cameras
           + np.repeat(np.array(reads.camera, np.int64), [len(v) for v in reads.vertex]))
    colour = np.concatenate(reads.colour).astype(np.float32)
    weight = np.concatenate(reads.weight).astype(np.float64)
    order = np.lexsort((colour @ LUMA, key))  # by pair, then by brightness within it
    key, colour, weight = key[order], colour[order], weight[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    cum = np.cumsum(weight)
    before = np.r_[0.0, cum][starts]
    total = cum[starts + counts - 1] - before
    median = np.searchsorted(cum, before + 0.5 * total, side="left")  # the weighted median's read, in its pair
    median = np.clip(median, starts, starts + counts - 1)
    pair = np.repeat(np.arange(len(starts)), counts)
    agree = np.abs(colour - colour[median][pair]).mean(1) <= tolerance
    w = np.where(agree, weight, 0.0)
    wsum = np.bincount(pair, weights=w, minlength=len(starts))
    mean = np.stack([np.bincount(pair, weights=w * colour[:, ch], minlength=len(starts)) for ch in range(3)], 1)
    mean = (mean / np.maximum(wsum, 1e-12)[:, None]).astype(np.float32)  # the median read always agrees: wsum > 0
    inliers = np.bincount(pair, weights=agree, minlength=len(starts)).astype(np.int64)
    return Consensus(key[starts], mean, inliers, counts.astype(np.int64))
