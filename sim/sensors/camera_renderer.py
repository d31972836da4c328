"""Renders what one camera sees: per-pixel rays (pinhole with radial-tangential distortion) cast onto the
road's height field and the cars' boxes (the nearer wins), giving scene radiance, true class labels and
distance per pixel. The camera's own response (gain, gamma, noise, JPEG) is camera_response.py's."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from daemon.spine.config import CameraConfig
from daemon.spine.semantic_classes import SemanticClass
from sim.world.linear_maps import apply_matrix
from sim.world.road_world import albedo_uv, semantic_uv
from sim.world.scene import HEADLIGHT_DIP_DEG, HEADLIGHT_POSITION, Scene
from sim.world.surface_raycast import MAX_RANGE_M, march, refine
from sim.world.traffic import CarBoxes, car_boxes, ray_box_hits

COARSE_STEP_PX = 8
CAR_RANGE_M = 150.0
SKY_HORIZON = np.array([0.62, 0.68, 0.74], np.float32)
NIGHT_SKY = np.array([0.002, 0.002, 0.003], np.float32)
NEAR_M = 0.3
BOX_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.abs(BOX_SIGNS[a] - BOX_SIGNS[b]).sum() == 2]


@dataclass
class CameraRig:
    """A camera's fixed geometry: unit rays of every pixel in the camera frame and its mounting."""

    config: CameraConfig
    rays: np.ndarray  # (H * W, 3) float32
    coarse_rows: np.ndarray
    coarse_cols: np.ndarray
    upsample_u: np.ndarray  # (H, W) float32 coarse-grid coordinates of each pixel
    upsample_v: np.ndarray
    camera_to_vehicle: np.ndarray  # (4, 4)


def camera_rig(config: CameraConfig) -> CameraRig:
    w, h = config.width, config.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    normalized = cv2.undistortPoints(pixels, config.intrinsics.matrix(), np.array(config.distortion),
                                     criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9))
    rays = np.concatenate([normalized.reshape(-1, 2), np.ones((w * h, 1))], axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rows = np.unique(np.r_[np.arange(0, h, COARSE_STEP_PX), h - 1])
    cols = np.unique(np.r_[np.arange(0, w, COARSE_STEP_PX), w - 1])
    uu = np.interp(np.arange(w), cols, np.arange(len(cols))).astype(np.float32)
    vv = np.interp(np.arange(h), rows, np.arange(len(rows))).astype(np.float32)
    up_u, up_v = np.meshgrid(uu, vv)
    return CameraRig(config, rays.astype(np.float32), rows, cols, up_u, up_v, config.extrinsics.matrix())


def camera_pose(scene: Scene, rig: CameraRig, time_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(rotation camera -> ENU, camera centre in ENU) at a true time."""
    rot_v, pos_v = scene.ego.pose(np.array([time_s]))
    rot = rot_v[0] @ rig.camera_to_vehicle[:3, :3]
    return rot, pos_v[0] + rot_v[0] @ rig.camera_to_vehicle[:3, 3]


@dataclass
class RenderedView:
    radiance: np.ndarray  # (H, W, 3) float32 linear scene radiance (1 = white paper in full daylight)
    labels: np.ndarray  # (H, W) uint8 true class: map classes, OBSTACLE for cars, BACKGROUND for sky
    depth: np.ndarray  # (H, W) float32 distance along the ray (inf for sky)


def _headlight(scene: Scene, time_s: float, points: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
    """Illuminance from the car's (dipped) headlights at world points, (N,)."""
    rot_v, pos_v = scene.ego.pose(np.array([time_s]))
    lamp = (pos_v[0] + rot_v[0] @ HEADLIGHT_POSITION).astype(np.float32)
    dip = np.radians(HEADLIGHT_DIP_DEG)
    axis = (rot_v[0] @ np.array([np.cos(dip), 0.0, -np.sin(dip)])).astype(np.float32)
    v = points - lamp
    r = np.sqrt(np.einsum("ni,ni->n", v, v))
    cos_off = (v @ axis) / np.maximum(r, 1e-3)
    theta0 = np.radians(scene.scenario.lighting.headlight_half_angle_deg)
    cone = np.exp(-2.0 * (1.0 - cos_off) / theta0**2)
    e = scene.scenario.lighting.headlight * (10.0 / np.maximum(r, 4.0)) ** 2 * cone
    if normals is not None:
        e = e * np.clip(-np.einsum("ni,ni->n", v, normals) / np.maximum(r, 1e-3), 0, 1) * 3.0
    return e.astype(np.float32)


def _ground(scene: Scene, rig: CameraRig, origin: np.ndarray, dirs: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Distance, atlas coordinates and hit flags of every pixel's ray on the height field."""
    h, w = rig.config.height, rig.config.width
    grid = dirs.reshape(h, w, 3)[np.ix_(rig.coarse_rows, rig.coarse_cols)].reshape(-1, 3)
    coarse = march(scene.world, origin, np.ascontiguousarray(grid))
    inverse = np.where(np.isfinite(coarse), 1.0 / coarse, 0.0).astype(np.float32)
    inverse = inverse.reshape(len(rig.coarse_rows), len(rig.coarse_cols))
    guess = cv2.remap(inverse, rig.upsample_u, rig.upsample_v, cv2.INTER_LINEAR)
    t0 = np.where(guess > 1.0 / MAX_RANGE_M, 1.0 / np.maximum(guess, 1e-6), MAX_RANGE_M).astype(np.float32)
    # In the image's own (H, W) shape the lookups need no reshaping for OpenCV.
    t, u, v, hit = refine(scene.world, origin, dirs.reshape(h, w, 3), t0, iterations=2)
    return t.ravel(), u.ravel(), v.ravel(), hit.ravel()


def _cars(rig: CameraRig, cars: CarBoxes, rot: np.ndarray, origin: np.ndarray, dirs: np.ndarray,
          depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest car hit per pixel: (car index or -1, face normal in ENU, point height fraction in the box)."""
    cfg = rig.config
    n = dirs.shape[0]
    index = np.full(n, -1, np.int32)
    normal = np.zeros((n, 3), np.float32)
    height = np.zeros(n, np.float32)
    rot_cw = rot.T
    k, dist = cfg.intrinsics.matrix(), np.array(cfg.distortion)
    for i in range(len(cars.centre)):
        if np.linalg.norm(cars.centre[i] - origin) > CAR_RANGE_M:
            continue
        corners = cars.centre[i] + (BOX_SIGNS * cars.half[i]) @ cars.rotation[i].T
        cam = (corners - origin) @ rot_cw.T
        front = cam[:, 2] > NEAR_M
        if not front.any():
            continue
        points = [cam[front]]
        for a, b in EDGES:  # where the box's edges cross the near plane
            if front[a] != front[b]:
                f = (NEAR_M - cam[a, 2]) / (cam[b, 2] - cam[a, 2])
                points.append((cam[a] + f * (cam[b] - cam[a]))[None])
        px, _ = cv2.projectPoints(np.concatenate(points), np.zeros(3), np.zeros(3), k, dist)
        px = px.reshape(-1, 2)
        c0, r0 = np.floor(np.clip(px.min(axis=0), -1e6, 1e6)).astype(int) - 2
        c1, r1 = np.ceil(np.clip(px.max(axis=0), -1e6, 1e6)).astype(int) + 2
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, cfg.width - 1), min(r1, cfg.height - 1)
        if c0 > c1 or r0 > r1:
            continue
        rr, cc = np.mgrid[r0:r1 + 1, c0:c1 + 1]
        pix = (rr * cfg.width + cc).ravel()
        t, face = ray_box_hits(origin, dirs[pix], cars.centre[i], cars.rotation[i], cars.half[i])
        nearer = t < depth[pix]
        pix, t, face = pix[nearer], t[nearer], face[nearer]
        depth[pix] = t
        index[pix] = i
        normal[pix] = apply_matrix(face, cars.rotation[i])
        up = cars.rotation[i][:, 2].astype(np.float32)
        local_z = (origin - cars.centre[i].astype(np.float32)) @ up + t * (dirs[pix] @ up)
        height[pix] = local_z / np.float32(cars.half[i][2])
    return index, normal, height


def _car_radiance(scene: Scene, time_s: float, cars: CarBoxes, index: np.ndarray, normal: np.ndarray,
                  height: np.ndarray, points: np.ndarray) -> np.ndarray:
    light = scene.scenario.lighting
    colour = cars.colour[index]
    side = np.abs(normal[:, 2]) < 0.5
    glass = side & (height > 0.15)
    colour = np.where(glass[:, None], np.float32(0.04), colour)
    colour = np.where((side & (height < -0.55))[:, None], np.float32(0.03), colour)
    if light.mode == "day":
        e = light.ambient + light.sun * np.maximum(normal @ scene.sun_direction.astype(np.float32), 0)
        rad = colour * e[:, None]
        rad += np.where(glass, 0.12 * light.ambient, 0)[:, None] * SKY_HORIZON
    else:
        e = light.ambient + _headlight(scene, time_s, points, normal)
        rad = colour * e[:, None]
    return rad.astype(np.float32)


def render_view(scene: Scene, rig: CameraRig, time_s: float) -> RenderedView:
    """The camera's view at a true time (mid-exposure)."""
    cfg = rig.config
    h, w = cfg.height, cfg.width
    rot, origin = camera_pose(scene, rig, time_s)
    origin32 = origin.astype(np.float32)
    dirs = apply_matrix(rig.rays, rot)
    t, u, v, hit = _ground(scene, rig, origin32, dirs)
    np.nan_to_num(u, copy=False)
    np.nan_to_num(v, copy=False)
    depth = np.where(hit, t, np.inf).astype(np.float32)
    cars = car_boxes(scene.world, scene.traffic, scene.ego, time_s)
    car_index, car_normal, car_height = _cars(rig, cars, rot, origin32, dirs, depth)
    on_car = car_index >= 0
    ground = hit & ~on_car
    u2, v2 = u.reshape(h, w), v.reshape(h, w)

    labels = semantic_uv(scene.world, u2, v2).ravel()
    labels[~ground] = SemanticClass.BACKGROUND
    labels[on_car] = SemanticClass.OBSTACLE

    light = scene.scenario.lighting
    # Haze: 1 on a near surface, 0 for the sky (depth inf); folds in the atlas's 1/255 scale.
    haze = np.exp(depth * np.float32(-1.0 / light.fog_distance_m))
    if light.mode == "day":
        radiance = cv2.remap(scene.lit_atlas, u2, v2, cv2.INTER_LINEAR).reshape(-1, 3).astype(np.float32)
        far = SKY_HORIZON * np.float32((light.ambient + light.sun) / 1.15)
    else:
        radiance = albedo_uv(scene.world, u2, v2).reshape(-1, 3).astype(np.float32)
        points = origin32 + np.minimum(t, MAX_RANGE_M)[:, None] * dirs
        radiance *= (light.ambient + _headlight(scene, time_s, points, None))[:, None]
        far = NIGHT_SKY
    if on_car.any():
        idx = np.flatnonzero(on_car)
        points = origin32 + depth[idx, None] * dirs[idx]
        radiance[idx] = 255.0 * _car_radiance(scene, time_s, cars, car_index[idx], car_normal[idx],
                                              car_height[idx], points)
    radiance *= (haze * np.float32(1 / 255))[:, None]
    radiance += far * (1 - haze)[:, None]
    return RenderedView(radiance.reshape(h, w, 3), labels.reshape(h, w), depth.reshape(h, w))


def project_points(rig: CameraRig, rot: np.ndarray, origin: np.ndarray, points: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) of ENU points and whether each lies in front of the camera."""
    cam = (np.asarray(points, np.float64) - origin) @ rot
    front = cam[:, 2] > 0.1
    px, _ = cv2.projectPoints(cam, np.zeros(3), np.zeros(3), rig.config.intrinsics.matrix(),
                              np.array(rig.config.distortion))
    return px.reshape(-1, 2), front
