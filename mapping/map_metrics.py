"""Map quality figures: PSNR on road pixels (held-out and training views, valid pixels only), mIoU of the
rendered semantics, Elev-error (mean distance from Lidar ground points to the surface, as the paper
defines it) and the mean absolute elevation error against a true elevation raster."""

from __future__ import annotations

import numpy as np

from mapping.mesh_renderer import sampled_pixels
from mapping.road_map import NO_LABEL, RoadMap, WindowIndex, render_view
from mapping.road_mesh import locate
from mapping.scene_data import CameraModel, GroundTruth, Keyframe, Trajectory
from mapping.semantic_classes import NUM_MAP_CLASSES, ROAD_SURFACE_CLASSES

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


def miou_pct(conf: np.ndarray) -> float | None:
    inter = np.diag(conf).astype(np.float64)
    union = conf.sum(0) + conf.sum(1) - inter
    present = union > 0
    return float(100.0 * np.mean(inter[present] / union[present])) if present.any() else None


def observed_triangles(road_map: RoadMap, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle under each point, restricted to triangles whose three vertices were supervised."""
    ids, w, ok = locate(road_map.mesh, xy)
    ok &= (road_map.observed[np.where(ok[:, None], ids, 0)] > 0).all(1)
    return ids, w, ok


def elev_error_cm(road_map: RoadMap, points: np.ndarray | None) -> float | None:
    """Mean distance (cm) from Lidar ground points over the reconstructed area to the surface (the
    perpendicular distance to the triangle under each point)."""
    if points is None or len(points) == 0:
        return None
    ids, _, ok = observed_triangles(road_map, points[:, :2])
    if not ok.any():
        return None
    ids, p = ids[ok], points[ok]
    v = np.concatenate([road_map.mesh.xy[ids], road_map.z_now[ids][..., None]], -1)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return float(100.0 * np.mean(np.abs(np.einsum("ij,ij->i", p - v[:, 0], n))))


def elev_mae_gt_cm(road_map: RoadMap, gt: GroundTruth | None) -> float | None:
    """Mean |z - z_true| (cm) over true-raster cells inside the reconstructed area."""
    if gt is None:
        return None
    xy = gt.cell_centres().reshape(-1, 2)
    z_true = gt.elevation_m.reshape(-1)
    ids, w, ok = observed_triangles(road_map, xy)
    ok &= np.isfinite(z_true)
    if not ok.any():
        return None
    z = (road_map.z_now[ids[ok]] * w[ok]).sum(1)
    return float(100.0 * np.mean(np.abs(z - z_true[ok])))


def evaluate_views(
    road_map: RoadMap,
    cameras: dict[str, CameraModel],
    views: list[Keyframe],
    trajectory: Trajectory,
    window_before_m: float,
    window_after_m: float,
    stride: int = EVAL_STRIDE,
) -> tuple[float | None, np.ndarray]:
    """Mean per-view PSNR on road pixels and the summed semantic confusion matrix, over the pixels that
    see the mapped surface (faces whose vertices were all supervised)."""
    windows = WindowIndex.of(road_map.mesh)
    mapped = (road_map.observed[road_map.mesh.faces] > 0).all(1)
    psnrs, conf = [], np.zeros((NUM_MAP_CLASSES, NUM_MAP_CLASSES), np.int64)
    road = np.array(ROAD_SURFACE_CLASSES)
    for kf in views:
        s = float(trajectory.along_track_at(kf.timestamp))
        faces = windows.faces(s - min(window_before_m, BEHIND_CAMERA_M), s + window_after_m)
        camera = cameras[kf.camera]
        view = render_view(road_map, faces[mapped[faces]], kf, camera, stride)
        at = sampled_pixels(camera, stride)
        image, semantics = kf.image.reshape(-1, 3)[at], kf.semantics.ravel()[at]
        road_pixels = view.hit & np.isin(semantics, road)
        value = psnr_db(view.rgb, image.astype(np.float32) / 255.0, road_pixels)
        if value is not None:
            psnrs.append(value)
        labelled = view.hit & (semantics < NUM_MAP_CLASSES) & (view.labels != NO_LABEL)
        conf += confusion(view.labels, semantics, labelled)
    return (float(np.mean(psnrs)) if psnrs else None), conf


def _evenly(views: list[Keyframe], count: int) -> list[Keyframe]:
    """At most `count` of `views`, evenly spaced in their order."""
    if len(views) <= count:
        return list(views)
    return [views[i] for i in np.linspace(0, len(views) - 1, count).astype(int)]


def evaluate_map(
    road_map: RoadMap,
    cameras: dict[str, CameraModel],
    holdout: list[Keyframe],
    train: list[Keyframe],
    trajectory: Trajectory,
    lidar_points: np.ndarray | None,
    gt: GroundTruth | None,
    window_before_m: float,
    window_after_m: float,
) -> dict:
    psnr, conf = evaluate_views(road_map, cameras, _evenly(holdout, HOLDOUT_VIEWS_EVALUATED), trajectory,
                                window_before_m, window_after_m)
    some_train = _evenly(train, TRAIN_VIEWS_EVALUATED)
    psnr_train, _ = evaluate_views(road_map, cameras, some_train, trajectory, window_before_m, window_after_m)
    return {
        "psnr_db": psnr,
        "psnr_train_db": psnr_train,
        "miou_pct": miou_pct(conf) if road_map.semantic_logits is not None else None,
        "elev_error_cm": elev_error_cm(road_map, lidar_points),
        "elev_mae_gt_cm": elev_mae_gt_cm(road_map, gt),
    }
