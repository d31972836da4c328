"""A tiny synthetic drive for the mapping tests: a textured, sloped and cross-falling road seen by moving
cameras, rendered by an independent numpy ray caster (march + bisection on the analytic height field)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from daemon.spine.config import Extrinsics
from daemon.spine.semantic_classes import SemanticClass
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.scene_data import CameraModel, GroundTruth, Keyframe

ROAD_HALF_WIDTH_M = 4.0


@dataclass(frozen=True)
class Surface:
    slope: float = 0.04
    crossfall: float = 0.05
    bump_m: float = 0.15

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.slope * x + self.crossfall * y + self.bump_m * np.sin(x / 4.0)


def texture(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Albedo (..., 3) in [0, 1] and class id at ground points."""
    grain = 0.5 + 0.25 * np.sin(3.1 * x + 1.7 * np.sin(2.3 * y)) * np.cos(2.7 * y - 0.9 * x)
    albedo = np.stack([0.30 + 0.25 * grain, 0.30 + 0.22 * grain, 0.32 + 0.2 * grain], -1)
    label = np.full(x.shape, SemanticClass.ROAD, np.uint8)
    lane = (np.abs(np.abs(y) - 1.75) < 0.12) & (np.mod(x, 3.0) < 1.8)
    centre = np.abs(y) < 0.08
    label[lane | centre] = SemanticClass.LANE_MARKING
    albedo[lane | centre] = (0.92, 0.92, 0.9)
    off_road = np.abs(y) > ROAD_HALF_WIDTH_M
    label[off_road] = SemanticClass.BACKGROUND
    albedo[off_road] = np.stack([0.25 + 0.1 * grain, 0.45 + 0.1 * grain, 0.2 + 0.0 * grain], -1)[off_road]
    return albedo, label


def cast(surface: Surface, origin: np.ndarray, rays: np.ndarray, max_range: float = 60.0) -> np.ndarray:
    """Ray parameter t of the first hit (NaN for none); rays (P, 3) world."""
    horizontal = np.linalg.norm(rays[:, :2], axis=1)
    ts = np.linspace(0.0, 1.0, 160)[None, :] ** 2 * (max_range / np.maximum(horizontal, 1e-6))[:, None]
    p = origin + ts[..., None] * rays[:, None, :]
    above = p[..., 2] - surface.height(p[..., 0], p[..., 1])
    below = above < 0
    first = np.argmax(below, axis=1)
    hit = below.any(1) & (first > 0)
    lo = ts[np.arange(len(ts)), np.maximum(first - 1, 0)]
    hi = ts[np.arange(len(ts)), first]
    for _ in range(25):
        mid = 0.5 * (lo + hi)
        q = origin + mid[:, None] * rays
        under = q[:, 2] < surface.height(q[:, 0], q[:, 1])
        hi = np.where(under, mid, hi)
        lo = np.where(under, lo, mid)
    return np.where(hit, 0.5 * (lo + hi), np.nan)


def camera_rig(width: int = 160, height: int = 90) -> dict[str, tuple[CameraModel, np.ndarray, float]]:
    """name -> (model, T_vehicle_camera, gain): a bright front camera and a darker front-left one."""
    f = 0.5 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    front = CameraModel("front", K, (-0.05, 0.01, 0.0, 0.0, 0.0), width, height)
    left = CameraModel("left", K, (0.0, 0.0, 0.0, 0.0, 0.0), width, height)
    return {
        "front": (front, Extrinsics(translation_m=(1.8, 0, 1.5), rotation_rpy_deg=(-100, 0, -90)).matrix(), 1.15),
        "left": (left, Extrinsics(translation_m=(1.6, 0.7, 1.4), rotation_rpy_deg=(-105, 0, -60)).matrix(), 0.7),
    }


@dataclass
class Scene:
    keyframes: list[Keyframe]
    cameras: dict[str, CameraModel]
    trajectory: HorizontalTrack
    lidar: np.ndarray
    gt: GroundTruth
    surface: Surface
    reference_height_m: float


def make_scene(
    length_m: float = 30.0,
    speed_mps: float = 5.0,
    rate_hz: float = 5.0,
    width: int = 160,
    height: int = 90,
    surface: Surface = Surface(),
    cameras: tuple[str, ...] = ("front", "left"),
    seed: int = 0,
) -> Scene:
    rng = np.random.default_rng(seed)
    ref = 0.5
    duration = length_m / speed_mps
    times = np.arange(0.0, duration + 1e-9, 0.05)
    x = speed_mps * times
    traj = HorizontalTrack(times, np.stack([x, 0 * x, surface.height(x, 0 * x) + ref], 1))
    rig = camera_rig(width, height)
    keyframes = []
    for t in np.arange(0.0, duration - 1e-9, 1.0 / rate_hz):
        T_wv = np.eye(4)
        T_wv[:3, 3] = [speed_mps * t, 0.0, surface.height(np.array(speed_mps * t), np.array(0.0)) + ref]
        for name in cameras:
            cam, T_vc, gain = rig[name]
            T_wc = T_wv @ T_vc
            vv, uu = np.mgrid[0:cam.height, 0:cam.width]
            pix = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64)
            n = cv2.undistortPoints(pix[:, None], cam.K, np.array(cam.distortion),
                                    criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10))[:, 0]
            rays = np.concatenate([n, np.ones((len(n), 1))], 1) @ T_wc[:3, :3].T
            tt = cast(surface, T_wc[:3, 3], rays)
            hit = np.isfinite(tt)
            p = T_wc[:3, 3] + np.nan_to_num(tt)[:, None] * rays
            albedo, label = texture(p[:, 0], p[:, 1])
            rgb = np.where(hit[:, None], np.clip(albedo * gain, 0, 1), (0.6, 0.7, 0.9))
            rgb = rgb + rng.normal(0, 0.005, rgb.shape)
            label = np.where(hit, label, SemanticClass.BACKGROUND).astype(np.uint8)
            image = np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8).reshape(cam.height, cam.width, 3)
            keyframes.append(Keyframe(name, float(t), T_wc, image, label.reshape(cam.height, cam.width)))
    lx = rng.uniform(0, length_m + 20, 20000)
    ly = rng.uniform(-ROAD_HALF_WIDTH_M, ROAD_HALF_WIDTH_M, len(lx))
    lidar = np.stack([lx, ly, surface.height(lx, ly) + rng.normal(0, 0.01, len(lx))], 1)
    res = 0.2
    gx, gy = np.meshgrid(np.arange(0, length_m + 20, res), np.arange(-ROAD_HALF_WIDTH_M, ROAD_HALF_WIDTH_M, res))
    gt = GroundTruth(surface.height(gx, gy), (0.0, -ROAD_HALF_WIDTH_M), res)
    return Scene(keyframes, {n: rig[n][0] for n in cameras}, traj, lidar, gt, surface, ref)
