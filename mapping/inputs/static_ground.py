"""The Lidar ground points the scans agree on: the road stands still, what moves over it does not.

One scan's ground filter (mapping.inputs.lidar_ground) keeps the points near the lowest of their 0.5 m cell; where
a passing car hides the road of a cell in that scan, the lowest points of its side or wheels (a few cm above the
road) are the cell's lowest and are kept. With few points under a vertex (an oncoming lane, far from the Lidar)
the Lidar detail then lifts the surface there by centimetres, and a label read through a surface 2 cm too high
lands 10 cm short at 7 m from a camera 1.5 m up. Over all the scans of a drive the road of that cell is seen
again once the car has gone: a point is kept when it lies within `tolerance_m` of the lowest point of its
`cell_m` cell over all scans, or when points of at least `min_scans` scans (itself counted) lie at its height in
that cell (a curb top, or any other raised but static ground); a point on something that moved is neither.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StaticGround:
    cell_m: float = 0.1  # the cells heights are compared in
    tolerance_m: float = 0.02  # kept within this of the cell's lowest point over all scans ...
    min_scans: int = 2  # ... or with points of this many scans at its height (in bins of tolerance_m, two offsets)


def static_index(points: np.ndarray, scan: np.ndarray, settings: StaticGround = StaticGround()) -> np.ndarray:
    """Which of the ground `points` (N, 3), of scans `scan` (N,) int, are static ground (increasing indices)."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    cell = np.floor(points[:, :2] / settings.cell_m).astype(np.int64)
    cell_key = (cell[:, 0] - cell[:, 0].min()) * (int(cell[:, 1].max() - cell[:, 1].min()) + 1) + \
        (cell[:, 1] - cell[:, 1].min())
    _, cell_id = np.unique(cell_key, return_inverse=True)
    cell_id = cell_id.ravel()
    low = np.full(int(cell_id.max()) + 1, np.inf)
    np.minimum.at(low, cell_id, points[:, 2])
    z = (points[:, 2] - low[cell_id]) / settings.tolerance_m  # >= 0
    keep = z < 1.0
    # the others need points of other scans at their height: only points at least half a bin up share a bin
    # with them, so only those are counted (most points lie at their cell's lowest)
    pool = np.flatnonzero(z >= 0.5)
    if not len(pool):
        return np.flatnonzero(keep)
    _, scan_id = np.unique(scan[pool], return_inverse=True)
    scan_id = scan_id.ravel().astype(np.int64)
    n_scans = int(scan_id.max()) + 1
    supported = np.zeros(len(pool), bool)
    for offset in (0.0, 0.5):  # height bins of tolerance_m, and the same shifted by half a bin
        level = np.floor(z[pool] + offset).astype(np.int64)
        key = cell_id[pool] * (int(level.max()) + 1) + level
        pairs = np.unique(key * n_scans + scan_id)  # each (bin, scan) once
        keys, scans_per_key = np.unique(pairs // n_scans, return_counts=True)
        supported |= scans_per_key[np.searchsorted(keys, key)] >= settings.min_scans
    keep[pool[supported]] = True
    return np.flatnonzero(keep)
