"""Pose refinement (the fast fit, `mapper.pose_refinement`): corrections of the trajectory's poses fitted to the map,
so that every keyframe sees the road where the others see it.

The correction is a function of the distance along the track: a (dx, dy, dz, droll, dpitch, dyaw) at knots
`knot_spacing_m` apart, linear in between, applied to the vehicle's pose on the left (the rotation in ENU about the
vehicle's reference point), so the cameras of one moment move together and a held-out keyframe takes the correction
of its place on the track without its image being used. It is fitted in rounds, coarse to fine, one per `blur_px`
entry: each blurs the training keyframes' grey images by that sigma, reads them at the mesh vertices (on the fitted
surface) with the current corrections into a mean grey value per vertex, picks per metre of track the
`samples_per_m` vertices of at least `min_views` views whose mean changes most to a neighbour (lane markings' edges,
texture), and fits the knots with Adam: each step reads every view of those vertices at its current pose and takes
the Huber error of each view against the vertex's mean over its views that step (a photometric bundle adjustment
against the map; a gain and offset per view take the cameras' and exposures' differences), plus a prior pulling each
knot towards zero and a smoothness term between neighbouring knots. Pixels a mask marks as obstacles or unlabelled
are not used; views without a mask use every pixel (the robust loss bounds what a car in view can pull).

The map is then observed with the corrected poses (mapping.fits.fast_fit.observe). With Lidar ground points and
their firing times, their registration (mapping.fits.lidar_registration) has already fitted each knot's height,
roll and pitch and re-placed the ground before the surface fit: the knots start from it and hold those three axes,
only x, y and yaw are fitted here. Without them (`lidar_registration` off, no Lidar, the live and fleet windows)
the Lidar ground and the camera-only elevation keep the poses they were made with.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from daemon.spine.mapper_config import PoseRefinementConfig
from daemon.spine.semantic_classes import NUM_MAP_CLASSES
from mapping.fits.photometric_elevation import grey_image
from mapping.fits.vertex_observations import bilinear, label_at, project_points
from mapping.localization.trajectory import HorizontalTrack, Trajectory
from mapping.method.adam import Adam, CosineDecay
from mapping.method.compute_device import optimisation_loop
from mapping.method.descent import Descent
from mapping.method.mesh_renderer import project
from mapping.method.road_map import RoadMap, WindowIndex
from mapping.method.scene_data import CameraModel, Keyframe

METRE_UNIT = 0.1  # the knots' translation is optimised in units of 10 cm ...
RADIAN_UNIT = float(np.deg2rad(1.0))  # ... and their rotation in degrees: one Adam step size suits both


@dataclass(frozen=True)
class PoseCorrections:
    """Corrections of the vehicle pose along the track: knot k at distance knots_s[k] (m, horizontal)."""

    knots_s: np.ndarray  # (K,) increasing
    position_m: np.ndarray  # (K, 3) ENU translation
    rotation_rad: np.ndarray  # (K, 3) ENU rotation vector, applied on the left about the reference point

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The correction (position (M, 3), rotation vector (M, 3)) at distances `s`, linear between knots."""
        def interpolated(values: np.ndarray) -> np.ndarray:
            return np.stack([np.interp(s, self.knots_s, values[:, k]) for k in range(3)], 1)
        return interpolated(self.position_m), interpolated(self.rotation_rad)

    def figures(self) -> dict:
        """What the metrics say of the corrections: the knots and the RMS / largest correction."""
        moved = np.linalg.norm(self.position_m, axis=1)
        turned = np.rad2deg(np.linalg.norm(self.rotation_rad, axis=1))
        return {"knots": len(self.knots_s), "position_rms_cm": 100.0 * float(np.sqrt((moved ** 2).mean())),
                "position_max_cm": 100.0 * float(moved.max()), "rotation_rms_deg": float(np.sqrt((turned ** 2).mean())),
                "rotation_max_deg": float(turned.max())}


def cv2_rodrigues_batch(rotvec: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotation matrices of (M, 3) rotation vectors."""
    return np.stack([cv2.Rodrigues(np.asarray(r, np.float64))[0] for r in rotvec])


def corrected(keyframes: list[Keyframe], trajectory: HorizontalTrack, corrections: PoseCorrections) -> list[Keyframe]:
    """The keyframes with the corrections at their place on the track applied to their poses."""
    if not keyframes:
        return []
    times = np.array([kf.timestamp for kf in keyframes])
    position, rotation = corrections.at(trajectory.horizontal_distance_at(times))
    reference = reference_points(trajectory, times)
    rotations = cv2_rodrigues_batch(rotation)
    out = []
    for kf, dp, dR, ref in zip(keyframes, position, rotations, reference, strict=True):
        T = np.eye(4)
        T[:3, :3] = dR @ kf.T_world_camera[:3, :3]
        T[:3, 3] = ref + dp + dR @ (kf.T_world_camera[:3, 3] - ref)
        out.append(replace(kf, T_world_camera=T))
    return out


def corrected_trajectory(trajectory: Trajectory, path: HorizontalTrack, corrections: PoseCorrections) -> Trajectory:
    """The vehicle's trajectory with the corrections applied to each pose (at its place on `path`, the trajectory's
    horizontal track the corrections were fitted along; on the left, about the reference point, as `corrected`)."""
    seconds = (trajectory.times_ns - trajectory.times_ns[0]) / 1e9 + path.times[0]
    position, rotation = corrections.at(path.horizontal_distance_at(seconds))
    rotations = Rotation.from_rotvec(rotation) * trajectory.rotations
    return Trajectory(trajectory.times_ns, trajectory.positions + position, rotations.as_quat(),
                      trajectory.origin_lat_deg, trajectory.origin_lon_deg, trajectory.origin_alt_m)


def reference_points(trajectory: HorizontalTrack, times: np.ndarray) -> np.ndarray:
    """The vehicle's reference point (M, 3) at `times` (s), which the corrections turn about."""
    return np.stack([np.interp(times, trajectory.times, trajectory.positions[:, k]) for k in range(3)], 1)


@dataclass
class _Views:
    """The training keyframes as the optimisation reads them: blurred grey images in one flat buffer."""

    grey: list[np.ndarray]  # per keyframe (H, W) float32 in [0, 1], blurred
    s: np.ndarray  # (V,) distance along the track


def _blurred_grey(keyframes: list[Keyframe], blur_px: float) -> list[np.ndarray]:
    out = []
    for kf in keyframes:
        grey = grey_image(kf)[..., 0] / 255.0
        out.append(cv2.GaussianBlur(grey, (0, 0), blur_px) if blur_px > 0 else grey)
    return out


def _visible(road_map: RoadMap, windows: WindowIndex, kf: Keyframe, s: float, camera: CameraModel,
             behind_m: float, ahead_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices in the keyframe's reach it sees (not where its mask says obstacle / unlabelled): ids, their
    world points and their pixels."""
    a, b = np.searchsorted(windows.vertex_s, [s - behind_m, s + ahead_m])
    ids = windows.vertex_order[a:b]
    points = np.concatenate([road_map.mesh.xy[ids], road_map.z_now[ids, None].astype(np.float64)], 1)
    uv, ok = project_points(points, camera, kf.T_world_camera)
    ids, points, uv = ids[ok], points[ok], uv[ok]
    if kf.semantics is not None:
        good = label_at(kf, uv) < NUM_MAP_CLASSES
        ids, points, uv = ids[good], points[good], uv[good]
    return ids, points, uv


def _selected_pairs(road_map: RoadMap, windows: WindowIndex, views: list[Keyframe], grey: list[np.ndarray],
                    s: np.ndarray, cameras: dict[str, CameraModel], settings: PoseRefinementConfig, behind_m: float,
                    ahead_m: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices the fit compares the views at and who sees them: per metre of track the `samples_per_m`
    vertices of at least `min_views` views whose mean grey value over those views changes most to a neighbour;
    returns per (view, vertex) pair the view, the vertex's slot among the selected and its world point."""
    n = road_map.mesh.num_vertices
    total, count = np.zeros(n), np.zeros(n)
    seen = []
    for kf, g, si in zip(views, grey, s, strict=True):
        ids, points, uv = _visible(road_map, windows, kf, float(si), cameras[kf.camera], behind_m, ahead_m)
        total[ids] += bilinear(g[..., None], uv)[:, 0]
        count[ids] += 1
        seen.append((ids, points))
    mean = np.where(count >= settings.min_views, total / np.maximum(count, 1), np.nan)
    neighbours = road_map.mesh.neighbours
    around = np.where(neighbours >= 0, mean[np.maximum(neighbours, 0)], np.nan)
    with np.errstate(invalid="ignore"):
        texture = np.nanmax(np.abs(around - mean[:, None]), axis=1, initial=0.0)
    texture = np.where(np.isfinite(mean) & np.isfinite(texture), texture, 0.0)
    usable = np.flatnonzero(texture > 0)
    metre = np.floor(road_map.mesh.s[usable]).astype(np.int64)
    order = np.lexsort((rng.random(len(usable)), -texture[usable], metre))  # by metre, most textured first
    metre = metre[order]
    rank = np.arange(len(order)) - np.searchsorted(metre, metre)
    chosen = usable[order[rank < settings.samples_per_m]]
    slot = np.full(n, -1, np.int64)
    slot[chosen] = np.arange(len(chosen))
    view_of, slots, points = [], [], []
    for v, (ids, p) in enumerate(seen):
        mine = slot[ids] >= 0
        view_of.append(np.full(int(mine.sum()), v, np.int64))
        slots.append(slot[ids[mine]])
        points.append(p[mine])
    return np.concatenate(view_of), np.concatenate(slots), np.concatenate(points)


def _rodrigues(w: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) rotation matrices of (M, 3) rotation vectors, smooth through zero."""
    theta2 = (w * w).sum(1) + 1e-12
    theta = theta2.sqrt()
    a = (torch.sin(theta) / theta)[:, None, None]
    b = ((1 - torch.cos(theta)) / theta2)[:, None, None]
    zero = torch.zeros_like(w[:, 0])
    k = torch.stack([zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], 1).reshape(-1, 3, 3)
    return torch.eye(3, dtype=w.dtype) + a * k + b * (k @ k)


def _image_reads(grey: list[np.ndarray]) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """The views' images in one flat tensor, each view's start in it and its width."""
    sizes = np.array([g.size for g in grey])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    return torch.from_numpy(np.concatenate([g.reshape(-1) for g in grey]).astype(np.float32)), starts, \
        np.array([g.shape[1] for g in grey], np.int64)


def _fit_round(knots: torch.Tensor, knot_s: np.ndarray, views: list[Keyframe], s: np.ndarray,
               reference: np.ndarray, grey: list[np.ndarray], cameras: dict[str, CameraModel],
               pairs: tuple[np.ndarray, np.ndarray, np.ndarray], settings: PoseRefinementConfig) -> tuple[float, float]:
    """Adam steps on the knots (K, 6, in METRE_UNIT / RADIAN_UNIT): each step reads every (view, vertex) pair
    of `pairs` at the views' current poses and pulls each view towards the mean of the vertex's views (held
    fixed within the step); the loss of the first and the last step."""
    flat, starts, widths = _image_reads(grey)
    view_of, slot_of, point_of = pairs
    vertices = int(slot_of.max()) + 1 if len(slot_of) else 0
    points = torch.from_numpy(point_of)
    view_t, slot_t = torch.from_numpy(view_of), torch.from_numpy(slot_of)
    camera_of = np.array([kf.camera for kf in views])
    by_camera = {name: torch.from_numpy(np.flatnonzero(camera_of[view_of] == name))
                 for name in dict.fromkeys(camera_of)}
    heights = {kf.camera: grey[v].shape[0] for v, kf in enumerate(views)}
    knot_i = np.clip(np.searchsorted(knot_s, s, side="right") - 1, 0, len(knot_s) - 2)
    frac = torch.from_numpy(np.clip((s - knot_s[knot_i]) / (knot_s[knot_i + 1] - knot_s[knot_i]), 0.0, 1.0))
    i0, i1 = torch.from_numpy(knot_i), torch.from_numpy(knot_i + 1)
    R0 = torch.from_numpy(np.stack([kf.T_world_camera[:3, :3] for kf in views]))
    p0 = torch.from_numpy(np.stack([kf.T_world_camera[:3, 3] for kf in views]))
    ref = torch.from_numpy(reference)
    start_t, width_t = torch.from_numpy(starts), torch.from_numpy(widths)
    gain = torch.zeros(len(views), requires_grad=True)  # log gain, mean-free
    offset = torch.zeros(len(views), requires_grad=True)  # mean-free
    opt = Adam([([knots], settings.lr), ([gain, offset], settings.photometric_lr)])
    decay = CosineDecay(opt, settings.steps, eta_min=0.1 * settings.lr)
    descent = Descent([opt], [decay])
    sigma = torch.tensor([settings.prior_m / METRE_UNIT] * 3 + [settings.prior_deg] * 3, dtype=torch.float64)
    smooth = torch.tensor([settings.smooth_m / METRE_UNIT] * 3 + [settings.smooth_deg] * 3, dtype=torch.float64)
    with optimisation_loop("pose refinement"):
        for _ in range(settings.steps):
            delta = knots[i0] * (1 - frac)[:, None] + knots[i1] * frac[:, None]
            dR = _rodrigues(delta[:, 3:] * RADIAN_UNIT)
            R = dR @ R0
            p = ref + delta[:, :3] * METRE_UNIT + (dR @ (p0 - ref)[..., None])[..., 0]
            cam = torch.einsum("sji,sj->si", R[view_t], points - p[view_t])  # R^T (X - p)
            value = torch.zeros(len(points), dtype=torch.float32)
            valid = torch.zeros(len(points), dtype=torch.bool)
            for name, idx in by_camera.items():
                camera = cameras[name]
                uv, ok = project(cam[idx], camera)
                ok = ok & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 2) & (uv[:, 1] >= 0) \
                    & (uv[:, 1] <= heights[name] - 2)
                uv = torch.where(ok[:, None], uv, torch.zeros_like(uv))
                u0, v0 = uv[:, 0].detach().floor(), uv[:, 1].detach().floor()
                fu, fv = (uv[:, 0] - u0).float(), (uv[:, 1] - v0).float()
                w = width_t[view_t[idx]]
                i = start_t[view_t[idx]] + v0.long() * w + u0.long()
                top = flat[i] * (1 - fu) + flat[i + 1] * fu
                bottom = flat[i + w] * (1 - fu) + flat[i + w + 1] * fu
                value = value.index_put((idx,), top * (1 - fv) + bottom * fv)
                valid = valid.index_put((idx,), ok)
            seen = torch.exp(gain - gain.mean())[view_t] * value + (offset - offset.mean())[view_t]
            weight = valid.float()
            views_at = torch.zeros(vertices).index_add_(0, slot_t, weight)
            mean = (torch.zeros(vertices).index_add_(0, slot_t, (seen * weight).detach())
                    / views_at.clamp(min=1))
            used = weight * (views_at[slot_t] >= 2)
            r = (seen - mean[slot_t]) / settings.photometric_sigma
            data = (torch.nn.functional.huber_loss(r, torch.zeros_like(r), reduction="none", delta=1.0)
                    * used).sum() / used.sum().clamp(min=1)
            prior = ((knots / sigma) ** 2).sum(1).mean()
            bend = (((knots[1:] - knots[:-1]) / smooth) ** 2).sum(1).mean()
            descent.step(data + settings.prior_weight * prior + settings.smooth_weight * bend)
    return descent.losses()


def knot_positions(trajectory: HorizontalTrack, spacing_m: float) -> np.ndarray:
    """The corrections' knots along the track: evenly from its start to its end, at most `spacing_m` apart."""
    length = float(trajectory.horizontal_distance()[-1])
    return np.linspace(0.0, length, max(2, int(np.ceil(length / spacing_m)) + 1))


HELD_BY_LIDAR = np.array([0, 0, 1, 1, 1, 0], bool)  # dz, roll, pitch: what the Lidar ground registration fits


def refine_poses(road_map: RoadMap, train: list[Keyframe], holdout: list[Keyframe],
                 cameras: dict[str, CameraModel], trajectory: HorizontalTrack, settings: PoseRefinementConfig,
                 behind_m: float, ahead_m: float, timings: dict[str, float], lidar: PoseCorrections | None = None
                 ) -> tuple[list[Keyframe], list[Keyframe], PoseCorrections, dict]:
    """The corrections fitted to the training keyframes (module docstring), and the training and held-out
    keyframes with them applied; figures for the metrics (`pose_refinement`). `lidar`: the Lidar ground
    registration's corrections (mapping.fits.lidar_registration, on the same knots): their height, roll and
    pitch are held, only x, y and yaw are fitted."""
    started = time.perf_counter()
    windows = WindowIndex.of(road_map.mesh)
    times = np.array([kf.timestamp for kf in train])
    s = trajectory.horizontal_distance_at(times)
    knot_s = knot_positions(trajectory, settings.knot_spacing_m)
    reference = reference_points(trajectory, times)
    initial = np.zeros((len(knot_s), 6))
    if lidar is not None:
        initial[:, :3], initial[:, 3:] = lidar.position_m / METRE_UNIT, lidar.rotation_rad / RADIAN_UNIT
        held = torch.from_numpy(HELD_BY_LIDAR)
        initial[:, ~HELD_BY_LIDAR] = 0.0
    knots = torch.tensor(initial, dtype=torch.float64, requires_grad=True)
    if lidar is not None:
        knots.register_hook(lambda grad: torch.where(held, torch.zeros_like(grad), grad))
    losses = []
    rng = np.random.default_rng(0)
    for blur in settings.blur_px:
        corrections = _as_corrections(knot_s, knots)
        views = corrected(train, trajectory, corrections)
        grey = _blurred_grey(views, blur)
        pairs = _selected_pairs(road_map, windows, views, grey, s, cameras, settings, behind_m, ahead_m, rng)
        # the knots are the whole correction: each round fits them on the uncorrected poses, from where they are
        losses.append(_fit_round(knots, knot_s, train, s, reference, grey, cameras, pairs, settings))
    corrections = _as_corrections(knot_s, knots)
    timings["pose_refinement_wall_s"] = time.perf_counter() - started
    figures = {**corrections.figures(), "loss_first_last": [list(pair) for pair in losses]}
    return corrected(train, trajectory, corrections), corrected(holdout, trajectory, corrections), corrections, figures


def _as_corrections(knot_s: np.ndarray, knots: torch.Tensor) -> PoseCorrections:
    values = knots.detach().numpy()
    return PoseCorrections(knot_s, values[:, :3] * METRE_UNIT, values[:, 3:] * RADIAN_UNIT)
