"""Camera-only elevation targets: a plane sweep along the vertical at the elevation lattice's nodes.

With no Lidar the fast path's residual elevation MLP learns from multi-view photometric consistency. At every
lattice node a small horizontal ground patch (`patch_samples` x `patch_samples` points, `patch_m` wide, on the
trajectory's z0 under each point) is raised by each candidate height h in [-span, +span] and projected into
every training keyframe that sees it; the grey values each view reads there are normalised per view (zero
mean, unit variance: robust to the cameras' different gains, offsets and white balance) and the views'
agreement is their mean pairwise normalised cross-correlation (NCC), got from the sum of the normalised
patches (|sum|^2 = V n + n sum_{v != w} NCC_vw) so each view is read once per candidate. The best height is
the NCC's maximum (parabolic sub-step; one on the edge of the range is no maximum and gives no height), and
its confidence how much it stands out: the peak less the best NCC at least `distinct_m` away (a repeated or
blank texture has a second peak as high; a textured patch seen consistently has one sharp one). The heights,
weighted by that confidence, are what the residual MLP is
fitted to (mapping.fits.observation_fit.fit_lattice), with the smoothness term over every node.

Views whose mask marks the patch centre as an obstacle or unlabelled are left out; so are views where the
patch is blank (grey standard deviation under `min_std`), and nodes seen by fewer than `min_views` views.
The nodes are swept in blocks along the track, each with the keyframes that reach it, so memory stays bounded
on long drives; the keyframes are split over `threads` threads, their sums added in a fixed order.

The sweep can also be centred on a given surface (`surface`: a height per mesh vertex, such as the residual
MLP's first fit to the sweep on z0), each patch lying on that surface (its crossfall and grade) and raised from
it: the fast fit sweeps a second time +-`photometric_refine_span_m` around its first fit and fits the MLP again
to those heights (mapping.fits.fast_fit.fit_surface_from_images). A false peak of the first sweep (a repeated
texture, an edge along the line of sight) is then outside the range, and a node whose truth lies beyond it gets
no height.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from daemon.spine.semantic_classes import NUM_MAP_CLASSES
from mapping.fits.vertex_observations import bilinear, project_camera_points
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.mesh_renderer import to_camera
from mapping.method.road_map import RoadMap
from mapping.method.road_mesh import locate
from mapping.method.scene_data import CameraModel, Keyframe

BLOCK_M = 20.0  # along-track length of the nodes swept at once
GRADE_M = 5.0  # the trajectory's grade at its ends is taken over this length
_GREY = np.array([0.299, 0.587, 0.114], np.float32)


@dataclass(frozen=True)
class SweepSettings:
    """The plane sweep's parameters (mapper.fast_fit.photometric_*; see daemon.spine.mapper_config)."""

    span_m: float = 0.4  # candidate heights z0 - span .. z0 + span ...
    step_m: float = 0.02  # ... this far apart
    patch_m: float = 0.6  # side of the square ground patch read at each node
    patch_samples: int = 7  # points along each side of it
    min_views: int = 3  # a node's candidate needs this many views
    min_std: float = 2.0  # grey levels (0-255): a view's patch below this is blank and left out
    distinct_m: float = 0.3  # the second peak is looked for at least this far from the best height (a sweep
    # narrower than that has none: its confidence is the peak NCC)
    behind_m: float = 3.0  # a keyframe reads the nodes from this far behind its trajectory point ...
    ahead_m: float = 12.0  # ... to this far ahead
    threads: int = 2


@dataclass(frozen=True)
class TrackEnds:
    """The grade of the trajectory's first and last `GRADE_M`: the mesh's z0 is held flat beyond its ends, where
    the road goes on climbing; the sweep is centred on the grade carried on there."""

    xy: np.ndarray  # (2, 2) first and last position
    tangent: np.ndarray  # (2, 2) unit direction of travel there
    grade: np.ndarray  # (2,) dz / ds there

    @staticmethod
    def of(trajectory: HorizontalTrack) -> TrackEnds:
        s = trajectory.horizontal_distance()
        p = trajectory.positions
        a, b = np.searchsorted(s, [min(GRADE_M, s[-1]), max(s[-1] - GRADE_M, 0.0)])
        a, b = max(int(a), 1), min(int(b), len(s) - 2)
        ends = [(0, a), (b, len(s) - 1)]
        tangent = np.array([p[j, :2] - p[i, :2] for i, j in ends])
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
        grade = np.array([(p[j, 2] - p[i, 2]) / max(s[j] - s[i], 1e-9) for i, j in ends])
        return TrackEnds(p[[0, -1], :2].copy(), tangent, grade)

    def offset(self, xy: np.ndarray) -> np.ndarray:
        """(...) height (m) the grade adds at points `xy` (..., 2) before the start or past the end, 0 between."""
        before = np.maximum(-((xy - self.xy[0]) @ self.tangent[0]), 0.0)
        after = np.maximum((xy - self.xy[1]) @ self.tangent[1], 0.0)
        return (after * self.grade[1] - before * self.grade[0]).astype(np.float32)


@dataclass(frozen=True)
class LatticeNodes:
    """The elevation lattice's nodes inside the mesh: integer indices, world x, y, z0 and along-track s."""

    nodes: np.ndarray  # (K, 2) int64, node (i, j) at origin_xy + (i, j) * lattice_m
    xy: np.ndarray  # (K, 2) float64
    z0: np.ndarray  # (K,) float32
    s: np.ndarray  # (K,) float32
    ends: TrackEnds | None = None  # where the sweep is centred beyond the track's ends (None: on z0)


@dataclass(frozen=True)
class SweepResult:
    """Per node: the best residual height over z0 (m), its confidence (>= 0; 0: no usable height), its peak
    NCC and the views that saw it at the best height."""

    residual: np.ndarray  # (K,) float32
    confidence: np.ndarray  # (K,) float32
    peak_ncc: np.ndarray  # (K,) float32
    views: np.ndarray  # (K,) int32


def lattice_nodes(road_map: RoadMap, lattice_m: float, trajectory: HorizontalTrack | None = None) -> LatticeNodes:
    """The lattice nodes (of the elevation MLP's lattice, relative to its origin) that lie inside the mesh."""
    mesh = road_map.mesh
    origin = np.asarray(road_map.elevation.origin_xy)
    nodes = np.unique(np.rint((mesh.xy - origin) / lattice_m).astype(np.int64), axis=0)
    xy = origin + nodes * lattice_m
    ids, w, ok = locate(mesh, xy)
    nodes, xy, ids, w = nodes[ok], xy[ok], ids[ok], w[ok]
    z0 = (mesh.z0[ids] * w).sum(1).astype(np.float32)
    return LatticeNodes(nodes, xy, z0, mesh.s[ids[:, 0]], TrackEnds.of(trajectory) if trajectory else None)


def _patch_points(road_map: RoadMap, xy: np.ndarray, settings: SweepSettings, ends: TrackEnds | None,
                  surface: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(K, P, 3) ground patch points around the nodes `xy` on the vertex heights `surface` (None: at z0 plus the
    grade beyond the track's ends) and (K, P) whether each lies inside the mesh."""
    n = settings.patch_samples
    offsets = (np.arange(n) - (n - 1) / 2) * (settings.patch_m / max(n - 1, 1))
    ox, oy = np.meshgrid(offsets, offsets, indexing="ij")
    p = xy[:, None, :] + np.stack([ox.ravel(), oy.ravel()], 1)[None]
    ids, w, ok = locate(road_map.mesh, p.reshape(-1, 2))
    z = road_map.mesh.z0 if surface is None else surface
    z = np.where(ok, (z[np.where(ok[:, None], ids, 0)] * w).sum(1), np.nan)
    if ends is not None and surface is None:
        z = z + ends.offset(p.reshape(-1, 2))
    return np.concatenate([p, z.reshape(len(xy), -1, 1)], 2), ok.reshape(len(xy), -1)


def grey_image(keyframe: Keyframe) -> np.ndarray:
    """(H, W, 1) float32 luma of the keyframe's image."""
    return (keyframe.image.astype(np.float32) @ _GREY)[..., None]


def sweep_keyframe(sums: np.ndarray, counts: np.ndarray, points: np.ndarray, heights: np.ndarray,
                   keyframe: Keyframe, camera: CameraModel, grey: np.ndarray, settings: SweepSettings) -> None:
    """Add one view's normalised patches of the nodes `points` (K, P, 3) raised by `heights` (D,) into `sums`
    (K, D, P) and its count into `counts` (K, D) where the whole patch is in view, textured and (by the mask,
    if any) on the map's classes."""
    T = keyframe.T_world_camera
    R = T[:3, :3]
    p = points.shape[1]
    near = np.isfinite(points[..., 2]).all(1)  # patches wholly on the mesh ...
    centre = np.where(near[:, None], points[:, p // 2], 0.0)
    near &= project_camera_points(to_camera(T, centre), camera)[1]  # ... whose centre is in view
    if not near.any():
        return
    rows = np.flatnonzero(near)
    cam0 = to_camera(T, points[rows].reshape(-1, 3)).reshape(len(rows), p, 3)  # raising by h adds h R^T e_z
    cam = cam0[:, None] + heights[None, :, None, None] * R[2][None, None, None]
    uv, ok = project_camera_points(cam.reshape(-1, 3), camera)
    ok = ok.reshape(len(rows), len(heights), p).all(2)
    uv = np.where(np.repeat(ok.reshape(-1), p)[:, None], uv, 0.0)
    values = bilinear(grey, uv)[:, 0].reshape(len(rows), len(heights), p)
    if keyframe.semantics is not None:
        mid = uv.reshape(len(rows), len(heights), p, 2)[:, :, p // 2]
        h, w = keyframe.semantics.shape
        label = keyframe.semantics.reshape(-1)[np.rint(mid[..., 1]).astype(np.int64).clip(0, h - 1) * w
                                               + np.rint(mid[..., 0]).astype(np.int64).clip(0, w - 1)]
        ok &= label < NUM_MAP_CLASSES
    mean = values.mean(2, keepdims=True)
    std = values.std(2, keepdims=True)
    ok &= std[..., 0] >= settings.min_std
    normalised = (values - mean) / np.maximum(std, 1e-6)
    sums[rows] += np.where(ok[..., None], normalised, 0.0).astype(np.float32)
    counts[rows] += ok


def _peaks(ncc: np.ndarray, valid: np.ndarray, heights: np.ndarray, distinct: int) -> tuple[np.ndarray, ...]:
    """Best height (parabolic sub-step), its NCC, the best NCC `distinct` or more steps away and whether the best
    is a maximum inside the swept range (valid candidates either side), per row."""
    masked = np.where(valid, ncc, -1e9)  # finite: a parabola through an invalid neighbour is never fitted
    best = masked.argmax(1)
    rows = np.arange(len(ncc))
    peak = masked[rows, best]
    lo, hi = np.maximum(best - 1, 0), np.minimum(best + 1, len(heights) - 1)
    a, b, c = masked[rows, lo], peak, masked[rows, hi]
    inner = (lo < best) & (hi > best) & valid[rows, lo] & valid[rows, hi]
    denom = np.where(inner, a - 2 * b + c, -1.0)
    shift = np.where(inner & (denom < 0), 0.5 * (a - c) / denom, 0.0).clip(-0.5, 0.5)
    step = heights[1] - heights[0] if len(heights) > 1 else 0.0
    far = np.abs(np.arange(len(heights))[None] - best[:, None]) >= distinct
    second = np.where(far & valid, ncc, -np.inf).max(1)
    return heights[best] + shift * step, peak, second, inner


def _sweep_views(ids: np.ndarray, block_s: np.ndarray, points: np.ndarray, heights: np.ndarray,
                 keyframes: list[Keyframe], keyframe_s: np.ndarray, cameras: dict[str, CameraModel],
                 greys: dict[int, np.ndarray], settings: SweepSettings) -> tuple[np.ndarray, np.ndarray]:
    """The sums and counts of keyframes `ids` over a block of nodes (along-track `block_s`, patches `points`)."""
    sums = np.zeros((len(block_s), len(heights), points.shape[1]), np.float32)
    counts = np.zeros((len(block_s), len(heights)), np.int32)
    for i in ids:
        kf, s = keyframes[i], keyframe_s[i]
        rows = np.flatnonzero((block_s >= s - settings.behind_m) & (block_s <= s + settings.ahead_m))
        if not len(rows):
            continue
        if i not in greys:
            greys[i] = grey_image(kf)
        sub_s, sub_c = sums[rows], counts[rows]
        sweep_keyframe(sub_s, sub_c, points[rows], heights, kf, cameras[kf.camera], greys[i], settings)
        sums[rows], counts[rows] = sub_s, sub_c
    return sums, counts


def sweep_heights(road_map: RoadMap, lattice: LatticeNodes, keyframes: list[Keyframe],
                  keyframe_s: np.ndarray, cameras: dict[str, CameraModel], settings: SweepSettings,
                  surface: np.ndarray | None = None) -> SweepResult:
    """The plane sweep at every node of `lattice` over the `keyframes` (their along-track positions
    `keyframe_s`), centred on z0 (and the grade beyond the track's ends) or on the vertex heights `surface`; the
    residuals are over the nodes' z0 either way. See the module docstring."""
    heights = np.arange(-settings.span_m, settings.span_m + 1e-9, settings.step_m)
    if surface is None:
        centre = lattice.ends.offset(lattice.xy) if lattice.ends is not None else np.zeros(len(lattice.xy), np.float32)
    else:
        ids, w, _ = locate(road_map.mesh, lattice.xy)  # the nodes lie on the mesh (lattice_nodes)
        centre = ((surface[ids] * w).sum(1) - lattice.z0).astype(np.float32)
    n = settings.patch_samples ** 2
    k = len(lattice.xy)
    residual, confidence = np.zeros(k, np.float32), np.zeros(k, np.float32)
    peak_ncc, views = np.zeros(k, np.float32), np.zeros(k, np.int32)
    greys: dict[int, np.ndarray] = {}
    order = np.argsort(lattice.s, kind="stable")
    edges = np.arange(lattice.s.min(), lattice.s.max() + BLOCK_M, BLOCK_M) if k else []
    for lo in edges:
        block = order[(lattice.s[order] >= lo) & (lattice.s[order] < lo + BLOCK_M)]
        if not len(block):
            continue
        points, inside = _patch_points(road_map, lattice.xy[block], settings, lattice.ends, surface)
        points[~inside.all(1)] = np.nan
        s_lo, s_hi = lattice.s[block].min(), lattice.s[block].max()
        reach = np.flatnonzero((keyframe_s + settings.ahead_m >= s_lo) & (keyframe_s - settings.behind_m <= s_hi))
        block_s = lattice.s[block]
        with ThreadPoolExecutor(settings.threads, thread_name_prefix="photometric-sweep") as pool:
            futures = [pool.submit(_sweep_views, reach[i::settings.threads], block_s, points, heights, keyframes,
                                   keyframe_s, cameras, greys, settings) for i in range(settings.threads)]
            parts = [f.result() for f in futures]
        sums, counts = parts[0]
        for more_s, more_c in parts[1:]:
            sums += more_s
            counts += more_c
        v = counts.astype(np.float64)
        ncc = ((sums.astype(np.float64) ** 2).sum(2) - v * n) / np.maximum(n * v * (v - 1), 1.0)
        valid = counts >= settings.min_views
        distinct = max(1, int(round(settings.distinct_m / settings.step_m)))
        best, peak, second, inner = _peaks(ncc, valid, heights, distinct)
        has = valid.any(1) & inner  # a best height on the range's edge is no maximum: the truth may lie beyond
        second = np.where(np.isfinite(second), second, 0.0)
        prior = centre[block]
        residual[block] = np.where(has, best + prior, prior)
        confidence[block] = np.where(has, np.clip(peak - np.maximum(second, 0.0), 0.0, None), 0.0)
        peak_ncc[block] = np.where(has, peak, 0.0)
        views[block] = np.where(has, counts[np.arange(len(block)), np.argmax(np.where(valid, ncc, -np.inf), 1)], 0)
        for i in [i for i in greys if keyframe_s[i] + settings.ahead_m < lo + BLOCK_M]:
            del greys[i]  # the blocks go along the track: views behind it are done
    return SweepResult(residual, confidence, peak_ncc, views)
