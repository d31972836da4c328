"""The surface's Lidar detail: what the smooth elevation cannot hold, taken from the Lidar ground points.

The elevation MLP (a 22-d encoding at the window's 160 m scale, fitted on a 0.5 m lattice) is smooth at the
metre scale: it rounds a 15 cm curb step over about a metre and leaves centimetre bumps out. A label or a
colour read through a surface that is 2 cm too high lands 13 cm short at 10 m from a camera 1.5 m up, so
curbs come out twice as wide and lane markings lose their edges. This step (beyond the paper's model, which
has no per-vertex elevation) adds to every vertex a detail height so that the mesh's piecewise-linear
surface passes through the Lidar ground points under it, by least squares over the points' barycentric
weights, solved by a few Jacobi passes. A vertex with few points is held by a prior of `prior` points: at
its neighbours' mean detail when `neighbours` is given (the fast fit), else at zero detail (the smooth surface).
Where the Lidar's points are sparse (a far lane, the road ahead of a drive's end: one point per several
vertices) the zero prior left a vertex without a point of its own on the smooth surface between vertices pulled
to their points, centimetres off, and labels read through it landed off by several times that; the neighbours'
prior carries the points' detail across those vertices (world 1: lane IoU 80.3 -> 84.4 %). It weighs 0.03 of a
point, so there is no smoothness term where points are: it would round the curb again.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from tqdm import tqdm

from mapping.method.mesh_location import Located


def fit_lidar_detail(z: np.ndarray, located: Located, heights: np.ndarray, passes: int, prior: float,
                     threads: int, progress: bool = False, neighbours: np.ndarray | None = None) -> np.ndarray:
    """Add the detail to the vertex elevations `z` (N,) in place, for the Lidar ground points placed by
    `located` with heights `heights` (M,); returns the detail (N,). Each pass's sums are split over the points
    into `threads` parts (numpy's gathers and bincount run partly without the GIL), added in a fixed order.
    `progress`: a bar of the passes with its ETA on stderr."""
    n = len(z)
    inside = np.flatnonzero(located.inside)
    parts = [(located.ids[part], located.weights[part], heights[part].astype(np.float32))
             for part in np.array_split(inside, threads)]

    def support(part) -> np.ndarray:
        ids, w, _ = part
        return np.bincount(ids.ravel(), w.ravel(), minlength=n)

    def pull(part) -> np.ndarray:
        ids, w, target = part
        residual = target - (z[ids] * w).sum(1)
        return np.bincount(ids.ravel(), (w * residual[:, None]).ravel(), minlength=n)

    detail = np.zeros(n, np.float32)
    with ThreadPoolExecutor(threads, thread_name_prefix="lidar-detail") as pool:
        total = (sum(pool.map(support, parts)) + prior).astype(np.float32)
        for _ in tqdm(range(passes), desc="lidar detail", unit="pass", disable=not progress, mininterval=0.5):
            toward = 0.0 if neighbours is None else _neighbour_mean(detail, neighbours)
            step = ((sum(pool.map(pull, parts)) - prior * (detail - toward)) / total).astype(np.float32)
            detail += step
            z += step
    return detail


def _neighbour_mean(detail: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """(N,) mean detail of each vertex's neighbours (N, 6; -1: none), 0 for a vertex without any."""
    present = neighbours >= 0
    values = np.where(present, detail[np.maximum(neighbours, 0)], 0.0).sum(1)
    return (values / np.maximum(present.sum(1), 1)).astype(np.float32)
