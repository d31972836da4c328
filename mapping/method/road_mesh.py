"""The road mesh: an equilateral-triangle lattice cut to a corridor around the trajectory (pure functions).

Lattice node (r, c) lies at x = x0 + (c + (r % 2) / 2) * a, y = y0 + r * a * sqrt(3) / 2, so every face
is an equilateral triangle of side a and any (x, y) maps to its triangle by arithmetic (`locate`).
Each vertex also keeps its initial elevation z0 (trajectory height minus the reference-point height at
the nearest along-track position) and that along-track position s (for the paper's 80 m windows).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mapping.localization.trajectory import HorizontalTrack

_ROW_CHUNK = 256  # lattice rows per corridor query (bounds the temporary memory)
_RESAMPLE_M = 0.25  # trajectory resampling step for distance queries
_BLOCK_M = 1.0  # squares of the coarse corridor test that spares most lattice nodes a distance query


@dataclass(frozen=True)
class RoadMesh:
    side_m: float
    origin: tuple[float, float]  # (x0, y0) of lattice node (0, 0)
    node_index: np.ndarray  # (R, C) int32 vertex id of each lattice node, -1 outside the corridor
    rc: np.ndarray  # (N, 2) int32 lattice row/column of each vertex
    xy: np.ndarray  # (N, 2) float64 world x, y
    z0: np.ndarray  # (N,) float32 initial elevation
    s: np.ndarray  # (N,) float32 along-track position of the nearest trajectory point
    faces: np.ndarray  # (F, 3) int32, counter-clockwise seen from above
    neighbours: np.ndarray  # (N, 6) int32 adjacent vertices, -1 where missing

    @property
    def row_spacing_m(self) -> float:
        return self.side_m * np.sqrt(3.0) / 2.0

    @property
    def num_vertices(self) -> int:
        return len(self.xy)

    def edges(self) -> np.ndarray:
        """(E, 2) undirected edges i < j."""
        i = np.repeat(np.arange(self.num_vertices), 6)
        j = self.neighbours.reshape(-1)
        keep = j > i
        return np.stack([i[keep], j[keep]], 1)


def node_xy(rc: np.ndarray, origin: tuple[float, float], side_m: float) -> np.ndarray:
    r, c = rc[..., 0].astype(np.float64), rc[..., 1].astype(np.float64)
    x = origin[0] + (c + 0.5 * (rc[..., 0] % 2)) * side_m
    y = origin[1] + r * side_m * np.sqrt(3.0) / 2.0
    return np.stack([x, y], -1)


def _resampled_track(trajectory: HorizontalTrack) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s_traj = trajectory.horizontal_distance()
    s = np.append(np.arange(0.0, s_traj[-1], _RESAMPLE_M), s_traj[-1])
    xy = np.stack([np.interp(s, s_traj, trajectory.positions[:, k]) for k in range(2)], 1)
    tangent = np.gradient(xy, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return s, xy, tangent


def _blocks_near_track(tree: cKDTree, lo: np.ndarray, hi: np.ndarray, half_width_m: float) -> np.ndarray:
    """(X, Y) bool over _BLOCK_M squares from `lo` covering `hi`: the squares that may hold a point within
    `half_width_m` of the track (their centre within that plus half their diagonal). Only the nodes in them
    are looked up in the tree: a drive's bounding box is mostly far from its track, and most of its lattice
    nodes need no lookup."""
    shape = np.floor((hi - lo) / _BLOCK_M).astype(np.int64) + 1
    ix, iy = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    centres = lo + (np.stack([ix.ravel(), iy.ravel()], 1) + 0.5) * _BLOCK_M
    reach = half_width_m + _BLOCK_M / np.sqrt(2.0)
    dist, _ = tree.query(centres, distance_upper_bound=reach + 1.0)
    return (dist <= reach).reshape(shape[0], shape[1])


def build_road_mesh(
    trajectory: HorizontalTrack,
    half_width_m: float,
    side_m: float,
    reference_height_m: float,
    flat: bool = False,
) -> RoadMesh:
    """Lattice vertices within `half_width_m` of the trajectory (xy), faces, neighbours and z0.

    flat=True gives RoMe's initial surface: one height (the mean trajectory height) everywhere.
    """
    s_dense, xy_dense, tangent = _resampled_track(trajectory)
    tree = cKDTree(xy_dense)
    h = side_m * np.sqrt(3.0) / 2.0
    lo = xy_dense.min(0) - half_width_m - side_m
    hi = xy_dense.max(0) + half_width_m + side_m
    origin = (float(np.floor(lo[0] / side_m) * side_m), float(np.floor(lo[1] / h) * h))
    rows = int(np.ceil((hi[1] - origin[1]) / h)) + 1
    cols = int(np.ceil((hi[0] - origin[0]) / side_m)) + 1
    node_index = np.full((rows, cols), -1, np.int32)
    near_block = _blocks_near_track(tree, lo, hi, half_width_m)
    rc_parts, s_parts = [], []
    count = 0
    for r0 in range(0, rows, _ROW_CHUNK):
        rr, cc = np.meshgrid(np.arange(r0, min(r0 + _ROW_CHUNK, rows)), np.arange(cols), indexing="ij")
        rc = np.stack([rr.ravel(), cc.ravel()], 1).astype(np.int32)
        xy = node_xy(rc, origin, side_m)
        block = np.floor((xy - lo) / _BLOCK_M).astype(np.int64)
        # the lattice reaches up to a side and a half past lo and hi, which lie beyond the corridor: nodes
        # outside the squares are not candidates
        candidate = (block >= 0).all(1) & (block < near_block.shape).all(1)
        candidate[candidate] = near_block[block[candidate, 0], block[candidate, 1]]
        rc, xy = rc[candidate], xy[candidate]
        dist, k = tree.query(xy, distance_upper_bound=half_width_m + _RESAMPLE_M)
        inside = dist <= half_width_m
        rc, xy, k = rc[inside], xy[inside], k[inside]
        s = s_dense[k] + np.einsum("ij,ij->i", xy - xy_dense[k], tangent[k])
        node_index[rc[:, 0], rc[:, 1]] = np.arange(count, count + len(rc), dtype=np.int32)
        count += len(rc)
        rc_parts.append(rc)
        s_parts.append(np.clip(s, 0.0, s_dense[-1]))
    rc = np.concatenate(rc_parts)
    s = np.concatenate(s_parts).astype(np.float32)
    s_traj = trajectory.horizontal_distance()
    z_traj = trajectory.positions[:, 2]
    if flat:
        z0 = np.full(len(rc), np.mean(z_traj) - reference_height_m, np.float32)
    else:
        z0 = (np.interp(s, s_traj, z_traj) - reference_height_m).astype(np.float32)
    return RoadMesh(
        side_m=side_m,
        origin=origin,
        node_index=node_index,
        rc=rc,
        xy=node_xy(rc, origin, side_m),
        z0=z0,
        s=s,
        faces=_faces(node_index, origin, side_m),
        neighbours=_neighbours(node_index, rc),
    )


def _faces(node_index: np.ndarray, origin: tuple[float, float], side_m: float) -> np.ndarray:
    lower, upper = node_index[:-1], node_index[1:]
    even = (np.arange(len(lower)) % 2 == 0)[:, None]
    l0, l1 = lower[:, :-1], lower[:, 1:]
    u0, u1 = upper[:, :-1], upper[:, 1:]
    # even strips: up (L c, L c+1, U c), down (U c, U c+1, L c+1); odd: up (L c, L c+1, U c+1), down (U c, U c+1, L c)
    up = np.stack([l0, l1, np.where(even, u0, u1)], -1).reshape(-1, 3)
    down = np.stack([u1, u0, np.where(even, l1, l0)], -1).reshape(-1, 3)
    faces = np.concatenate([up, down])
    faces = faces[(faces >= 0).all(1)]
    return faces.astype(np.int32)


def _neighbours(node_index: np.ndarray, rc: np.ndarray) -> np.ndarray:
    r, c = rc[:, 0].astype(np.int64), rc[:, 1].astype(np.int64)
    shift = np.where(r % 2 == 0, -1, 0)  # column of the left neighbour in the rows above/below
    offsets = [(0, -1, 0), (0, 1, 0), (-1, 0, 1), (-1, 1, 1), (1, 0, 1), (1, 1, 1)]
    out = np.full((len(rc), 6), -1, np.int32)
    rows, cols = node_index.shape
    for n, (dr, dc, uses_shift) in enumerate(offsets):
        rr = r + dr
        cc = c + dc + (shift if uses_shift else 0)
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        out[ok, n] = node_index[rr[ok], cc[ok]]
    return out


def used_vertices(ids: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(ids, return_inverse=True) for vertex ids in [0, num_vertices), in linear time: the sorted
    distinct ids and each entry's index among them (same shape as `ids`). The sort np.unique does took a
    third of a view's render."""
    mark = np.zeros(num_vertices, bool)
    mark[ids.ravel()] = True
    used = np.flatnonzero(mark)
    position = np.empty(num_vertices, np.int64)
    position[used] = np.arange(len(used))
    return used, position[ids]


def locate(mesh: RoadMesh, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The triangle under each point: vertex ids (M, 3), barycentric weights (M, 3), valid (M,).

    Within lattice strip r the point has height fraction t in [0, 1) and position f in [0, 1) between
    lower-row nodes cl and cl + 1; the up triangle is t <= 2 min(f, 1 - f), else a down triangle whose
    top edge lies on the upper row.
    """
    v = (xy[:, 1] - mesh.origin[1]) / mesh.row_spacing_m
    r = np.floor(v).astype(np.int64)
    t = v - r
    odd = r & 1
    q = (xy[:, 0] - mesh.origin[0]) / mesh.side_m - 0.5 * odd
    cl = np.floor(q).astype(np.int64)
    f = q - cl
    up = t <= 2.0 * np.minimum(f, 1.0 - f)
    right = f >= 0.5
    # vertex 0: the lower-row node; vertices 1, 2: the other two (columns in their rows)
    low_col = np.where(up | ~right, cl, cl + 1)
    apex = cl + odd  # upper-row column above the middle of lower nodes cl, cl + 1
    fd = np.where(right, f - 1.0, f)  # position relative to the down triangle's bottom node
    rows1 = np.where(up, r, r + 1)
    col1 = np.where(up, cl + 1, np.where(right, apex, apex - 1))
    col2 = np.where(up | ~right, apex, apex + 1)
    w = np.empty((len(xy), 3))
    w[:, 0] = np.where(up, 1.0 - f - 0.5 * t, 1.0 - t)
    w[:, 1] = np.where(up, f - 0.5 * t, 0.5 * t - fd)
    w[:, 2] = np.where(up, t, 0.5 * t + fd)
    rows, cols = mesh.node_index.shape
    rr = np.stack([r, rows1, r + 1], 1)
    cc = np.stack([low_col, col1, col2], 1)
    ok = ((rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)).all(1)
    ids = np.full((len(xy), 3), -1, np.int64)
    ids[ok] = mesh.node_index[rr[ok], cc[ok]]
    return ids, w, ok & (ids >= 0).all(1)
