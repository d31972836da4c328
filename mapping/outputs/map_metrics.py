"""Map quality figures: PSNR on road pixels (held-out and training views, valid pixels only), mIoU of the
rendered semantics (against the masks, or the true semantic grid), Elev-error (mean distance from Lidar
ground points to the surface, as the paper defines it), the mean absolute elevation error against a
true elevation raster, and two checks of artefacts: the saw tooth of the mapped area's edges and the share
of the map whose colour the views that see it contradict (smears)."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_closing, binary_erosion, binary_opening

from daemon.spine.semantic_classes import NUM_MAP_CLASSES, ROAD_SURFACE_CLASSES, SemanticClass
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.mesh_location import Located, all_observed
from mapping.method.mesh_renderer import sampled_pixels
from mapping.method.road_map import NO_LABEL, RoadMap, ViewGeometry, WindowIndex, view_geometry, view_labels, view_rgb
from mapping.method.road_mesh import locate
from mapping.method.scene_data import CameraModel, GroundTruth, Keyframe

TRAIN_VIEWS_EVALUATED = 12
HOLDOUT_VIEWS_EVALUATED = 36  # evenly spaced along the drive: evaluation costs the same on long drives
EVAL_STRIDE = 2  # views are rendered and compared at every 2nd pixel row and column
BEHIND_CAMERA_M = 10.0  # the cameras look forward: faces further behind the view's trajectory point are not drawn


def psnr_db(rendered: np.ndarray, observed: np.ndarray, mask: np.ndarray) -> float | None:
    """PSNR of [0, 1] images over the masked pixels only (None if the mask is empty)."""
    if not mask.any():
        return None
    mse = float(np.mean((rendered[mask] - observed[mask]) ** 2))
    return 10.0 * np.log10(1.0 / max(mse, 1e-12))


def confusion(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, n: int = NUM_MAP_CLASSES) -> np.ndarray:
    p, t = pred[mask].astype(np.int64), truth[mask].astype(np.int64)
    keep = (p < n) & (t < n)
    return np.bincount(t[keep] * n + p[keep], minlength=n * n).reshape(n, n)


def iou_pct(conf: np.ndarray) -> dict[str, float]:
    """IoU (%) of each class present in the truth or the prediction of a confusion matrix, by class name."""
    inter = np.diag(conf).astype(np.float64)
    union = conf.sum(0) + conf.sum(1) - inter
    return {SemanticClass(c).name.lower(): float(100.0 * inter[c] / union[c]) for c in np.flatnonzero(union > 0)}


def miou_pct(conf: np.ndarray) -> float | None:
    per_class = iou_pct(conf)
    return float(np.mean(list(per_class.values()))) if per_class else None


OBSERVED_BLOCK_M = 1.0  # the observed area is rasterised on blocks of this size to skip points far from it


def _near_observed(road_map: RoadMap, xy: np.ndarray) -> np.ndarray:
    """(M,) False where a point cannot lie in a triangle with an observed vertex: no observed vertex in its
    OBSERVED_BLOCK_M block or the 8 around it (a point is within one mesh side of its triangle's vertices)."""
    block = max(OBSERVED_BLOCK_M, road_map.mesh.side_m)
    seen = np.floor(road_map.mesh.xy[road_map.observed > 0] / block).astype(np.int64)
    near = np.zeros(len(xy), bool)
    if not len(seen):
        return near
    lo = seen.min(0) - 1
    shape = seen.max(0) - lo + 2
    marked = np.zeros(tuple(shape), bool)
    marked[tuple((seen - lo).T)] = True
    grown = marked.copy()  # marked blocks and the 8 around each (its border is empty: rolling wraps nothing in)
    for shift in ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        grown |= np.roll(marked, shift, axis=(0, 1))
    cell = np.floor(xy / block).astype(np.int64) - lo
    i, j = cell[:, 0], cell[:, 1]
    inside = np.flatnonzero((i >= 0) & (i < shape[0]) & (j >= 0) & (j < shape[1]))
    near[inside] = grown[i[inside], j[inside]]
    return near


def observed_triangles(road_map: RoadMap, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle under each point, restricted to triangles whose three vertices were supervised."""
    near = np.flatnonzero(_near_observed(road_map, xy))  # locate only points that can be in an observed triangle
    near_ids, near_w, near_ok = locate(road_map.mesh, xy[near])
    ids, w, ok = np.full((len(xy), 3), -1, np.int64), np.zeros((len(xy), 3)), np.zeros(len(xy), bool)
    ids[near], w[near], ok[near] = near_ids, near_w, near_ok & all_observed(road_map, near_ids, near_ok)
    return ids, w, ok


def truth_cells(gt: GroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and centres (M, 2) of every other true cell: 10 cm, the mesh resolution (the truth
    rasters are 5 cm); the truth metrics are taken on these cells."""
    h, w = gt.elevation_m.shape
    ii, jj = np.mgrid[0:h:2, 0:w:2]
    rows, cols = ii.ravel(), jj.ravel()
    return rows, cols, np.stack([gt.origin_xy[0] + cols * gt.resolution_m, gt.origin_xy[1] + rows * gt.resolution_m], 1)


@dataclass(frozen=True)
class MetricPoints:
    """Where the metrics read the map, located ahead of time: the Lidar ground points and the truth cells."""

    lidar: Located | None  # Located.of(mesh, the Lidar ground points' x, y)
    truth: Located | None  # Located.of(mesh, truth_cells(gt)[2])


def elev_error_cm(road_map: RoadMap, points: np.ndarray | None, located: Located | None = None) -> float | None:
    """Mean distance (cm) from Lidar ground points over the reconstructed area to the surface (the
    perpendicular distance to the triangle under each point). `located`: the points' Located, if made."""
    if points is None or len(points) == 0:
        return None
    ids, w, ok = located.observed(road_map) if located is not None else observed_triangles(road_map, points[:, :2])
    if not ok.any():
        return None
    ids, w, p = ids[ok], w[ok], points[ok]
    z = road_map.z_now
    z0, z1, z2 = z[ids[:, 0]], z[ids[:, 1]], z[ids[:, 2]]
    # a point's x, y lie on its triangle, so its distance to the triangle's plane is its height above the surface
    # times |n_z| / |n| of the triangle's normal n (as a cross product of its edges: 2x fewer operations than
    # the point-to-plane product with the normal normalised per point)
    gap = p[:, 2] - (z0 * w[:, 0] + z1 * w[:, 1] + z2 * w[:, 2])
    xy = road_map.mesh.xy
    a = xy[ids[:, 0]]
    e1, e2, dz1, dz2 = xy[ids[:, 1]] - a, xy[ids[:, 2]] - a, z1 - z0, z2 - z0
    nx, ny = e1[:, 1] * dz2 - dz1 * e2[:, 1], dz1 * e2[:, 0] - e1[:, 0] * dz2
    nz = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    return float(100.0 * np.mean(np.abs(gap) * np.abs(nz) / np.sqrt(nx * nx + ny * ny + nz * nz)))


def _at_truth_cells(road_map: RoadMap, gt: GroundTruth, located: Located | None):
    rows, cols, xy = truth_cells(gt)
    ids, w, ok = located.observed(road_map) if located is not None else observed_triangles(road_map, xy)
    return rows[ok], cols[ok], ids[ok], w[ok]


def elev_mae_gt_cm(road_map: RoadMap, gt: GroundTruth | None, located: Located | None = None) -> float | None:
    """Mean |z - z_true| (cm) over the truth cells (truth_cells) inside the reconstructed area with a true
    elevation. `located`: the truth cells' Located, if made."""
    if gt is None:
        return None
    rows, cols, ids, w = _at_truth_cells(road_map, gt, located)
    true = gt.elevation_m[rows, cols]
    known = np.isfinite(true)
    if not known.any():
        return None
    z = (road_map.z_now[ids[known]] * w[known]).sum(1)
    return float(100.0 * np.mean(np.abs(z - true[known])))


def bev_confusion(road_map: RoadMap, gt: GroundTruth | None, located: Located | None = None) -> np.ndarray | None:
    """Confusion (truth rows, map columns) of the map's semantics against the true semantic grid (bird's-eye
    view), over the truth cells (truth_cells) inside the labelled reconstructed area with a map class."""
    if gt is None or gt.semantic is None or road_map.semantic_logits is None:
        return None
    rows, cols, ids, w = _at_truth_cells(road_map, gt, located)
    true = gt.semantic[rows, cols]
    valid = (true < NUM_MAP_CLASSES) & road_map.labelled[ids].all(1)
    if not valid.any():
        return None
    logits = road_map.semantic_logits.detach().numpy()
    pred = (logits[ids[valid]] * w[valid][..., None]).sum(1).argmax(1)
    return confusion(pred, true[valid], np.ones(valid.sum(), bool))


@dataclass(frozen=True)
class _ViewSeen:
    """A view's geometry against its camera image: what its PSNR needs once the colours are fitted."""

    camera: str
    geometry: ViewGeometry
    observed: np.ndarray  # (H', W', 3) float32 camera image at the sampled pixels, [0, 1]
    road_pixels: np.ndarray  # (H', W') bool: pixels that see the mesh and show road surface (without a mask: every
    # pixel that sees the mesh, whatever stands on it)
    distance_m: np.ndarray  # (H', W') float32 distance from the camera to the surface the pixel sees (inf: none)
    confusion: np.ndarray  # (C, C) rendered semantics against the view's segmentation mask (zeros without one)
    masked: bool  # the view has semantics (a mask or a model's labels)


def _view_seen(road_map: RoadMap, cameras: dict[str, CameraModel], kf: Keyframe, trajectory: HorizontalTrack,
               window_before_m: float, window_after_m: float, windows: WindowIndex, mapped: np.ndarray,
               stride: int = EVAL_STRIDE) -> _ViewSeen:
    """One view over the pixels that see the mapped surface (faces whose vertices were all supervised)."""
    s = float(trajectory.horizontal_distance_at(kf.timestamp))
    faces = windows.faces(s - min(window_before_m, BEHIND_CAMERA_M), s + window_after_m)
    camera = cameras[kf.camera]
    geometry = view_geometry(road_map, faces[mapped[faces]], kf, camera, stride)
    at = sampled_pixels(camera, stride)
    image = kf.image.reshape(-1, 3)[at].astype(np.float32) / 255.0
    hit = geometry.hit.reshape(at.shape)
    distance = np.full(hit.size, np.inf, np.float32)
    w = geometry.weights.numpy()[..., None]
    seen_at = (np.concatenate([road_map.mesh.xy[geometry.tri], road_map.z_now[geometry.tri][..., None]], -1) * w).sum(1)
    distance[geometry.hit] = np.linalg.norm(seen_at - kf.T_world_camera[:3, 3], axis=1)
    distance = distance.reshape(at.shape)
    if kf.semantics is None:
        return _ViewSeen(kf.camera, geometry, image, hit, distance,
                         np.zeros((NUM_MAP_CLASSES, NUM_MAP_CLASSES), np.int64), False)
    semantics = kf.semantics.ravel()[at]
    labels = view_labels(road_map, geometry)
    labelled = hit & (semantics < NUM_MAP_CLASSES) & (labels != NO_LABEL)
    return _ViewSeen(kf.camera, geometry, image, hit & np.isin(semantics, np.array(ROAD_SURFACE_CLASSES)), distance,
                     confusion(labels, semantics, labelled), True)


DISTANCE_BANDS_M = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, np.inf))  # PSNR by distance from the camera


@dataclass(frozen=True)
class _ViewScore:
    """A shaded view's PSNR, and its sums for the figures pooled over views."""

    psnr: float | None
    band_squared_error: np.ndarray  # (bands,) summed over the band's pixels and channels
    band_values: np.ndarray  # (bands,) pixel channels summed over
    saturation: np.ndarray  # (2,) sums over the road pixels of the rendered and the observed HSV saturation
    pixels: int
    vertices: np.ndarray  # (V,) the vertices the view's road pixels see (each pixel: its triangle's nearest)
    vertex_residual: np.ndarray  # (V,) their pixels' mean absolute colour difference, rendered - observed


def _saturation(rgb: np.ndarray) -> np.ndarray:
    """HSV saturation of (N, 3) colours in [0, 1]: (max - min) / max, 0 for black."""
    top = rgb.max(axis=1)
    return np.where(top > 0, (top - rgb.min(axis=1)) / np.maximum(top, 1e-12), 0.0)


def _view_score(road_map: RoadMap, seen: _ViewSeen) -> _ViewScore:
    rendered = view_rgb(road_map, seen.geometry, seen.camera)
    road = seen.road_pixels
    squared = ((rendered - seen.observed) ** 2).sum(-1)
    bands = [road & (seen.distance_m >= lo) & (seen.distance_m < hi) for lo, hi in DISTANCE_BANDS_M]
    saturation = np.array([_saturation(rendered[road]).sum(), _saturation(seen.observed[road]).sum()])
    hit, geometry = seen.geometry.hit, seen.geometry
    on_road = road.ravel()[hit]
    nearest = geometry.tri[np.arange(len(geometry.tri)), geometry.weights.numpy().argmax(1)][on_road]
    residual = np.abs(rendered.reshape(-1, 3)[hit][on_road] - seen.observed.reshape(-1, 3)[hit][on_road]).mean(1)
    vertices, inverse, count = np.unique(nearest, return_inverse=True, return_counts=True)
    return _ViewScore(psnr_db(rendered, seen.observed, road), np.array([squared[b].sum() for b in bands]),
                      np.array([3 * b.sum() for b in bands], np.float64), saturation, int(road.sum()), vertices,
                      np.bincount(inverse, weights=residual, minlength=len(vertices)) / np.maximum(count, 1))


SMEAR_RESIDUAL = 0.1  # a view contradicts the map at a vertex where its pixels there differ by more (mean |RGB|)
SMEAR_MIN_VIEWS = 3  # vertices seen by fewer evaluated views are not judged


def smear_pct(scores: list[_ViewScore]) -> float | None:
    """Of the mapped vertices that at least SMEAR_MIN_VIEWS evaluated views see (on their PSNR pixels), the share
    (%) whose map colour at least half of those views contradict (their pixels there differ from the rendering by
    more than SMEAR_RESIDUAL, mean absolute RGB in [0, 1]). Something standing above the road (a car, a cyclist, a
    wall) lands on different ground from each view, radially away from each camera: where a map holds it, the
    views disagree with the map there; a thing in front of the road in one view contradicts one view only."""
    if not scores:
        return None
    ids = np.concatenate([v.vertices for v in scores])
    contradicted = np.concatenate([v.vertex_residual > SMEAR_RESIDUAL for v in scores])
    if not len(ids):
        return None
    views = np.bincount(ids)
    against = np.bincount(ids, weights=contradicted.astype(np.float64), minlength=len(views))
    judged = views >= SMEAR_MIN_VIEWS
    return float(100.0 * np.mean(2 * against[judged] >= views[judged])) if judged.any() else None


EDGE_CELL_M = 0.2  # the mapped area is rasterised on cells this size ...
EDGE_SMOOTH_M = 1.0  # ... and smoothed by a closing and an opening with a disc of this radius
EDGE_MAX_CELLS = 25_000_000  # a larger raster (a drive's bounding box of more than 1 km^2) is not measured


def edge_sawtooth_cm(road_map: RoadMap) -> float | None:
    """How jagged the mapped area's edge is (cm): the mapped area (the observed vertices on EDGE_CELL_M cells) and
    its smoothing (closed, then opened, by a disc of EDGE_SMOOTH_M) differ by an area; that area over the smoothed
    edge's length is the mean depth of the notches and teeth narrower than the disc. A straight or smoothly
    curving edge gives about 7 cm (the cells), a saw tooth of 0.8 m teeth 1 m apart on one of the two edges (each
    view's reach a wedge cut off at its far end, one per keyframe) 25 cm (tests/mapping/test_map_metrics.py)."""
    xy = road_map.mesh.xy[road_map.observed > 0]
    if len(xy) < 3:
        return None
    pad = int(np.ceil(EDGE_SMOOTH_M / EDGE_CELL_M)) + 2
    cell = np.floor((xy - xy.min(0)) / EDGE_CELL_M).astype(np.int64) + pad
    shape = cell.max(0) + pad + 1
    if shape[0] * shape[1] > EDGE_MAX_CELLS:
        return None
    mapped = np.zeros(tuple(shape), bool)
    mapped[cell[:, 0], cell[:, 1]] = True
    mapped = binary_closing(mapped, np.ones((3, 3), bool))  # solid between the lattice's nodes
    r = pad - 2
    yy, xx = np.mgrid[-r: r + 1, -r: r + 1]
    disc = yy * yy + xx * xx <= r * r
    smooth = binary_opening(binary_closing(mapped, disc), disc)
    edge_cells = (smooth & ~binary_erosion(smooth)).sum()
    if not edge_cells:
        return None
    return float(100.0 * (smooth ^ mapped).sum() / edge_cells)


def _pooled(scores: list[_ViewScore]) -> dict:
    """PSNR per distance band over the pixels of every view pooled (a band's mean squared error, then its PSNR),
    and the mean HSV saturation of the rendered and the observed road pixels with their ratio."""
    error = sum((v.band_squared_error for v in scores), np.zeros(len(DISTANCE_BANDS_M)))
    values = sum((v.band_values for v in scores), np.zeros(len(DISTANCE_BANDS_M)))
    bands = {f"{lo:g}-{hi:g} m" if np.isfinite(hi) else f"{lo:g}+ m":
             (10.0 * np.log10(n / max(e, 1e-12 * n)) if n > 0 else None)
             for (lo, hi), e, n in zip(DISTANCE_BANDS_M, error, values, strict=True)}
    pixels = sum(v.pixels for v in scores)
    rendered, observed = sum((v.saturation for v in scores), np.zeros(2)) / max(pixels, 1)
    return {"psnr_by_distance_db": bands if pixels else None,
            "saturation_rendered_pct": 100.0 * rendered if pixels else None,
            "saturation_observed_pct": 100.0 * observed if pixels else None,
            "saturation_ratio": rendered / observed if pixels and observed > 0 else None}


def _evenly(views: list[Keyframe], count: int) -> list[Keyframe]:
    """At most `count` of `views`, evenly spaced in their order."""
    if len(views) <= count:
        return list(views)
    return [views[i] for i in np.linspace(0, len(views) - 1, count).astype(int)]


@dataclass
class PendingEvaluation:
    """An evaluation started on its pool (start_evaluation) whose PSNRs wait for the map's colours."""

    road_map: RoadMap
    pool: ThreadPoolExecutor
    elev_error: Future
    elev_mae: Future
    bev_confusion: Future
    edge_sawtooth: Future
    held: list[Future]  # of _ViewSeen, held-out views
    trained: list[Future]  # of _ViewSeen, training views


def start_evaluation(
    road_map: RoadMap,
    cameras: dict[str, CameraModel],
    holdout: list[Keyframe],
    train: list[Keyframe],
    trajectory: HorizontalTrack,
    lidar_points: np.ndarray | None,
    gt: GroundTruth | None,
    window_before_m: float,
    window_after_m: float,
    threads: int,
    points: MetricPoints | None = None,
) -> PendingEvaluation:
    """Start every part of the evaluation that needs only the final surface and semantics (the elevation
    figures, the bird's-eye mIoU, each view's render and semantic confusion) as tasks on a pool of
    `threads` threads, the longest first: numpy and torch release the GIL in their array work (torch keeps
    one intra-op thread: two spun against each other on this 2-core machine). `points`: the Lidar points and
    truth cells placed on the mesh, if placed ahead of time (reconstruct does before the fits)."""
    windows = WindowIndex.of(road_map.mesh)
    mapped = (road_map.observed[road_map.mesh.faces] > 0).all(1)
    lidar_at, truth_at = (points.lidar, points.truth) if points is not None else (None, None)
    pool = ThreadPoolExecutor(threads, thread_name_prefix="evaluate")
    elev_error = pool.submit(elev_error_cm, road_map, lidar_points, lidar_at)
    elev_mae = pool.submit(elev_mae_gt_cm, road_map, gt, truth_at)
    bev = pool.submit(bev_confusion, road_map, gt, truth_at)
    edge = pool.submit(edge_sawtooth_cm, road_map)

    def views(keyframes: list[Keyframe], count: int) -> list[Future]:
        return [pool.submit(_view_seen, road_map, cameras, kf, trajectory, window_before_m, window_after_m, windows,
                            mapped) for kf in _evenly(keyframes, count)]

    return PendingEvaluation(road_map, pool, elev_error, elev_mae, bev, edge,
                             views(holdout, HOLDOUT_VIEWS_EVALUATED), views(train, TRAIN_VIEWS_EVALUATED))


PSNR_PIXELS = {  # which pixels the PSNRs are taken over, by whether the evaluated views have masks
    frozenset({True}): "road (the masks' road-surface pixels)",
    frozenset({False}): "mapped surface (no masks: every pixel that sees the mapped road, whatever stands on it)",
    frozenset({True, False}): "road where a view has a mask, else the mapped surface",
    frozenset(): "none (no views evaluated)",
}


def finish_evaluation(pending: PendingEvaluation) -> dict:
    """The metrics of a started evaluation, its views shaded with the map's colours as they are now.
    `psnr_pixels` says which pixels the PSNRs are over (PSNR_PIXELS); `psnr_by_distance_db` and the saturations
    are over the held-out views' same pixels, pooled (_pooled).
    `miou_mask_pct` compares rendered semantics with the held-out frames' segmentation masks; `miou_pct` is
    the bird's-eye mIoU against the true grid when the truth has one, else `miou_mask_pct`; `iou_pct` holds
    the per-class IoUs `miou_pct` is the mean of."""
    road_map = pending.road_map
    with pending.pool as pool:
        def scores(views: list[Future]) -> list[_ViewScore]:
            shaded = [pool.submit(_view_score, road_map, view.result()) for view in views]
            return [f.result() for f in shaded]

        def mean_psnr(views: list[_ViewScore]) -> float | None:
            values = [v.psnr for v in views if v.psnr is not None]
            return float(np.mean(values)) if values else None

        held, trained = scores(pending.held), scores(pending.trained)

        conf = sum((f.result().confusion for f in pending.held), np.zeros((NUM_MAP_CLASSES, NUM_MAP_CLASSES),
                                                                         np.int64))
        masked = {f.result().masked for f in pending.held + pending.trained}
        labelled = road_map.semantic_logits is not None
        bev = pending.bev_confusion.result()
        scored = bev if bev is not None else conf
        return {
            "psnr_db": mean_psnr(held),
            "psnr_train_db": mean_psnr(trained),
            "psnr_pixels": PSNR_PIXELS[frozenset(masked)],
            **_pooled(held),
            "miou_pct": miou_pct(scored) if labelled else None,
            "iou_pct": iou_pct(scored) if labelled else None,
            "miou_mask_pct": miou_pct(conf) if labelled else None,
            "elev_error_cm": pending.elev_error.result(),
            "elev_mae_gt_cm": pending.elev_mae.result(),
            "edge_sawtooth_cm": pending.edge_sawtooth.result(),
            "smear_pct": smear_pct(held + trained),
        }
