"""The simulated Lidar: every (column, beam) ray of the sensor cast from the pose at that column's firing time onto
the road and the cars, with range noise and dropouts, encoded into the sensor's real UDP packets. A LidarRig says
what the sensor is: the Ouster OS-128 of its metadata (drivers/lidar/ouster_encoder.py) here, a Velodyne of its
calibration in sim/sensors/velodyne_sim.py."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemon.spine.config import LidarConfig
from daemon.spine.semantic_classes import SemanticClass
from drivers.lidar.ouster_encoder import encode_frame_packets
from drivers.lidar.ouster_metadata import (
    OusterMetadata,
    metadata_to_json,
    parse_metadata,
    simulated_os128_metadata,
)
from drivers.lidar.ouster_packet_layout import packet_layout
from drivers.lidar.ouster_xyz import make_xyz_lut
from sim.world.linear_maps import apply_matrices
from sim.world.road_world import albedo_uv, semantic_uv
from sim.world.scene import Scene
from sim.world.surface_raycast import march, refine
from sim.world.traffic import car_boxes, ray_box_hits

RANGE_NOISE_M = 0.01
DROPOUT = 0.01
MIN_RANGE_M = 0.5
COARSE_COLUMNS = 8
CAR_RANGE_M = 120.0
NO_RETURN = 255


def write_sim_metadata(path: str | Path, columns_per_frame: int = 1024, fps: int = 10) -> OusterMetadata:
    """Write the simulated OS-128's metadata JSON (LEGACY profile) and return it."""
    meta = simulated_os128_metadata(columns_per_frame=columns_per_frame, fps=fps, udp_profile_lidar="LEGACY")
    Path(path).write_text(metadata_to_json(meta) + "\n")
    return meta


@dataclass
class LidarRig:
    direction: np.ndarray  # (W, H, 3) float32 unit ray directions in the sensor frame
    offset: np.ndarray  # (W, H, 3) float32 ray origins (range 0) in the sensor frame, metres
    sensor_to_vehicle: np.ndarray  # (4, 4)
    column_offset_s: np.ndarray  # (W,) firing time of each column after the scan's first
    columns_per_packet: int
    # (scan, sensor stamp of each column in ns) -> the scan's payloads (P, packet size) uint8 and the sensor time
    # of each packet (ns) as its driver publishes it
    encode: Callable[[LidarScanSim, np.ndarray], tuple[np.ndarray, np.ndarray]]


def ouster_rig(config: LidarConfig, metadata_path: str | Path) -> LidarRig:
    meta = parse_metadata(Path(metadata_path))
    if meta.columns_per_frame != config.columns_per_frame or meta.fps != config.rate_hz:
        raise ValueError(f"{metadata_path}: metadata mode {meta.lidar_mode} does not match the config "
                         f"({config.columns_per_frame}x{config.rate_hz})")
    lut = make_xyz_lut(meta)
    direction = np.moveaxis(lut.direction, 0, -1) * 1000.0
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    layout, w, k = packet_layout(meta), meta.columns_per_frame, meta.columns_per_packet

    def encode(scan: LidarScanSim, column_stamp_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pixels = {"range_mm": scan.range_mm, "reflectivity": scan.reflectivity, "signal": scan.signal,
                  "near_ir": scan.near_ir}
        return encode_frame_packets(layout, scan.frame_id, pixels, column_stamp_ns), column_stamp_ns[::k]

    return LidarRig(np.ascontiguousarray(direction, np.float32),
                    np.ascontiguousarray(np.moveaxis(lut.offset, 0, -1), np.float32), config.extrinsics.matrix(),
                    np.arange(w) / (w * meta.fps), k, encode)


@dataclass
class LidarScanSim:
    """One simulated frame; images are staggered (column = measurement id), as the packets carry them."""

    frame_id: int
    column_time_s: np.ndarray  # (W,) true firing time of each column
    range_mm: np.ndarray  # (H, W) uint32, 0 = no return
    reflectivity: np.ndarray  # (H, W) uint16
    signal: np.ndarray  # (H, W) uint16
    near_ir: np.ndarray  # (H, W) uint16
    hit_world: np.ndarray  # (W, H, 3) float32 noise-free ENU point of each return (NaN where none)
    hit_class: np.ndarray  # (W, H) uint8 class hit (OBSTACLE for cars, NO_RETURN for none)


def column_times(rig: LidarRig, start_s: float) -> np.ndarray:
    return start_s + rig.column_offset_s


def world_rays(scene: Scene, rig: LidarRig, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ENU ray origins and unit directions (W, H, 3) for columns fired at `times` (W,)."""
    rot_v, pos_v = scene.ego.pose(times)
    rot = rot_v @ rig.sensor_to_vehicle[:3, :3]
    pos = pos_v + rot_v @ rig.sensor_to_vehicle[:3, 3]
    dirs = apply_matrices(rig.direction, rot)
    origins = apply_matrices(rig.offset, rot) + pos.astype(np.float32)[:, None, :]
    return origins, dirs


def _surface(scene: Scene, origins: np.ndarray, dirs: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance (inf where none) and atlas coordinates of each ray's hit on the height field."""
    w, h, _ = dirs.shape
    cols = np.r_[np.arange(0, w, COARSE_COLUMNS), 0]  # the last coarse column wraps to the first
    coarse = march(scene.world, origins[cols].reshape(-1, 3), dirs[cols].reshape(-1, 3)).reshape(len(cols), h)
    inverse = np.where(np.isfinite(coarse), 1.0 / coarse, 0.0)
    pos = np.arange(w) / COARSE_COLUMNS
    i0 = np.minimum(pos.astype(int), len(cols) - 2)
    f = (pos - i0)[:, None]
    guess = inverse[i0] * (1 - f) + inverse[i0 + 1] * f
    either = np.maximum(inverse[i0], inverse[i0 + 1])
    guess = np.where((inverse[i0] > 0) & (inverse[i0 + 1] > 0), guess, either)
    t = np.full((w, h), np.inf, np.float32)
    u = np.zeros((w, h), np.float32)
    v = np.zeros((w, h), np.float32)
    todo = guess > 0
    if todo.any():
        tt, uu, vv, hit = refine(scene.world, origins[todo], dirs[todo], (1.0 / guess[todo]).astype(np.float32))
        t[todo] = np.where(hit, tt, np.inf)
        u[todo], v[todo] = uu, vv
    return t, u, v


def _cars(scene: Scene, rig: LidarRig, origins: np.ndarray, dirs: np.ndarray, mid_s: float,
          t: np.ndarray, cls: np.ndarray) -> None:
    """Let the cars occlude: update distances t and classes in place. Only the columns and beams whose
    azimuth and elevation can fall within a car's angular extent (seen from mid-sweep) are tested."""
    cars = car_boxes(scene.world, scene.traffic, scene.ego, mid_s)
    w, h = dirs.shape[:2]
    centre = origins[w // 2, h // 2].astype(np.float64)
    middle = dirs[:, h // 2]
    column_az = np.arctan2(middle[:, 1], middle[:, 0])
    beam_el = np.arcsin(np.clip(dirs[w // 2, :, 2], -1, 1))  # the car's pitch and roll tilt it a little
    # a column's beams spread about its middle one (the OS-128's up to 8.4 degrees, a VLS-128's 6.4), plus 2 degrees
    beam_az = np.arctan2(dirs[w // 2, :, 1], dirs[w // 2, :, 0])
    spread = np.abs((beam_az - column_az[w // 2] + np.pi) % (2 * np.pi) - np.pi).max()
    az_margin, el_margin = spread + np.radians(2.0), np.radians(4.0)
    for i in range(len(cars.centre)):
        d = cars.centre[i] - centre
        if np.linalg.norm(d[:2]) > CAR_RANGE_M:
            continue
        corners = cars.centre[i] + (_BOX_SIGNS * cars.half[i]) @ cars.rotation[i].T - centre
        flat = np.hypot(corners[:, 0], corners[:, 1])
        if flat.min() < 0.5:
            continue  # the sensor is above the car (never: it rides on our own roof)
        az0 = np.arctan2(d[1], d[0])
        rel = (np.arctan2(corners[:, 1], corners[:, 0]) - az0 + np.pi) % (2 * np.pi) - np.pi
        el = np.arctan2(corners[:, 2], flat)
        off = (column_az - az0 + np.pi) % (2 * np.pi) - np.pi - (rel.max() + rel.min()) / 2
        cols = np.flatnonzero(np.abs(off) < (rel.max() - rel.min()) / 2 + az_margin)
        beams = np.flatnonzero((beam_el > el.min() - el_margin) & (beam_el < el.max() + el_margin))
        if not len(cols) or not len(beams):
            continue
        sel = np.ix_(cols, beams)
        hit_t, _ = ray_box_hits(origins[sel].reshape(-1, 3), dirs[sel].reshape(-1, 3), cars.centre[i],
                                cars.rotation[i], cars.half[i])
        hit_t = hit_t.reshape(len(cols), len(beams))
        closer = hit_t < t[sel]
        t[sel] = np.where(closer, hit_t, t[sel])
        cls[sel] = np.where(closer, SemanticClass.OBSTACLE, cls[sel])


_BOX_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)


def simulate_scan(scene: Scene, rig: LidarRig, frame_id: int, start_s: float, rng: np.random.Generator
                  ) -> LidarScanSim:
    """The frame whose first column fires at true time start_s."""
    times = column_times(rig, start_s)
    origins, dirs = world_rays(scene, rig, times)
    t, u, v = _surface(scene, origins, dirs)
    cls = np.where(np.isfinite(t), semantic_uv(scene.world, u, v), NO_RETURN).astype(np.uint8)
    albedo_grey = np.zeros(t.shape, np.float32)
    if np.isfinite(t).any():
        albedo_grey = albedo_uv(scene.world, u, v).astype(np.float32).mean(axis=-1) / 255.0
    _cars(scene, rig, origins, dirs, float(times[len(times) // 2]), t, cls)
    car = cls == SemanticClass.OBSTACLE
    albedo_grey = np.where(car, 0.3, albedo_grey)
    max_range = 30.0 + 150.0 * albedo_grey
    valid = np.isfinite(t) & (t > MIN_RANGE_M) & (t < max_range) & (rng.random(t.shape) > DROPOUT)
    measured = t + rng.normal(0.0, RANGE_NOISE_M, t.shape).astype(np.float32)
    range_mm = np.where(valid, np.rint(np.where(valid, measured, 0) * 1000.0), 0).astype(np.uint32)
    reflect = np.where(valid, np.clip(albedo_grey * 255.0, 1, 255), 0)
    signal = np.where(valid, np.clip(reflect * 4000.0 / (np.where(valid, t, 1) ** 2 + 1.0) + 30, 0, 65535), 0)
    ambient = 600.0 if scene.scenario.lighting.mode == "day" else 20.0
    near_ir = np.clip(rng.normal(ambient, ambient * 0.1, t.shape), 0, 65535)
    hit_world = np.where(valid[..., None], origins + np.where(valid, t, 0)[..., None] * dirs, np.nan)
    return LidarScanSim(
        frame_id=frame_id, column_time_s=times, range_mm=range_mm.T.copy(),
        reflectivity=reflect.T.astype(np.uint16), signal=signal.T.astype(np.uint16),
        near_ir=near_ir.T.astype(np.uint16), hit_world=hit_world.astype(np.float32),
        hit_class=np.where(valid, cls, NO_RETURN).astype(np.uint8))
