"""The simulated car's true motion: speed and lane-keeping along the road, the reference point held
`vehicle.reference_height_m` above the surface under it, pitch and roll following the surface under the
wheels, sampled every millisecond with velocity, acceleration and body rates for the inertial sensors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from daemon.spine.config import VehicleConfig
from sim.world.road_atlas import lane_centre
from sim.world.road_world import RoadWorld, road_point, surface_height

STEP_S = 0.001
SMOOTHING_S = 0.05  # suspension and steering smooth the motion over about this time
GRAVITY = 9.80665
PAD_S = 1.0  # the trajectory extends this long before and after the drive


@dataclass
class EgoTrajectory:
    """Samples every STEP_S of the true drive time (seconds from the drive's start, -PAD_S..T+PAD_S)."""

    time_s: np.ndarray  # (N,)
    s: np.ndarray  # (N,) arc length along the road of the reference point
    position: np.ndarray  # (N, 3) ENU of the vehicle reference point
    rotation: np.ndarray  # (N, 3, 3) vehicle -> ENU
    velocity: np.ndarray  # (N, 3) ENU m/s
    acceleration: np.ndarray  # (N, 3) ENU m/s^2
    body_rate: np.ndarray  # (N, 3) angular velocity in the vehicle frame, rad/s
    speed: np.ndarray  # (N,) m/s along the path

    def _index(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = np.clip((np.asarray(t, np.float64) - self.time_s[0]) / STEP_S, 0, len(self.time_s) - 1.000001)
        i = u.astype(np.int64)
        return i, u - i

    def sample(self, field: str, t: np.ndarray) -> np.ndarray:
        """Linear interpolation of a per-sample field at times t (seconds)."""
        i, f = self._index(t)
        data = getattr(self, field)
        f = f.reshape(f.shape + (1,) * (data.ndim - 1))
        return data[i] * (1 - f) + data[i + 1] * f

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rotation (..., 3, 3) vehicle -> ENU, position (..., 3)) at times t."""
        return self.sample("rotation", t), self.sample("position", t)

    def quaternion_xyzw(self, t: np.ndarray) -> np.ndarray:
        rot, _ = self.pose(np.atleast_1d(t))
        return Rotation.from_matrix(rot).as_quat()


def _speed_profile(t: np.ndarray, mean: float, variation: float, rng: np.random.Generator) -> np.ndarray:
    p1, p2 = rng.uniform(0, 2 * np.pi, 2)
    return mean + variation * (0.7 * np.sin(2 * np.pi * t / 17.0 + p1) + 0.3 * np.sin(2 * np.pi * t / 6.5 + p2))


def _surface_angles(world: RoadWorld, position_xy: np.ndarray, yaw: np.ndarray, vehicle: VehicleConfig
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Pitch and roll that put the four wheels (rear axle at the reference point) on the surface."""
    c, s = np.cos(yaw), np.sin(yaw)
    half = vehicle.track_width_m / 2
    heights = {}
    for name, (dx, dy) in {"rl": (0.0, half), "rr": (0.0, -half), "fl": (vehicle.wheel_base_m, half),
                           "fr": (vehicle.wheel_base_m, -half)}.items():
        x = position_xy[:, 0] + c * dx - s * dy
        y = position_xy[:, 1] + s * dx + c * dy
        heights[name] = surface_height(world, x.astype(np.float32), y.astype(np.float32)).astype(np.float64)
    front = (heights["fl"] + heights["fr"]) / 2
    rear = (heights["rl"] + heights["rr"]) / 2
    left = (heights["fl"] + heights["rl"]) / 2
    right = (heights["fr"] + heights["rr"]) / 2
    pitch = -np.arctan2(front - rear, vehicle.wheel_base_m)
    roll = np.arctan2(left - right, vehicle.track_width_m)
    return pitch, roll


def drive_trajectory(world: RoadWorld, vehicle: VehicleConfig, seconds: float, rng: np.random.Generator
                     ) -> EgoTrajectory:
    """The ego car's motion for a drive of `seconds` (plus PAD_S either side)."""
    sc = world.scenario
    t = np.arange(-PAD_S, seconds + PAD_S + STEP_S / 2, STEP_S)
    speed = _speed_profile(t, sc.drive.speed_mps, sc.drive.speed_variation_mps, rng)
    s = sc.drive.start_s_m + np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * STEP_S)])
    s -= np.interp(0.0, t, s) - sc.drive.start_s_m
    phase = rng.uniform(0, 2 * np.pi)
    lateral = lane_centre(sc.road, sc.drive.ego_lane) + 0.12 * np.sin(2 * np.pi * t / 11.0 + phase)
    sigma = SMOOTHING_S / STEP_S
    xy = gaussian_filter1d(road_point(world, s, lateral), sigma, axis=0, mode="nearest")
    dxy = np.gradient(xy, STEP_S, axis=0)
    yaw = np.unwrap(np.arctan2(dxy[:, 1], dxy[:, 0]))
    pitch, roll = _surface_angles(world, xy, yaw, vehicle)
    pitch = gaussian_filter1d(pitch, 2 * sigma, mode="nearest")
    roll = gaussian_filter1d(roll, 2 * sigma, mode="nearest")
    ground = surface_height(world, xy[:, 0].astype(np.float32), xy[:, 1].astype(np.float32)).astype(np.float64)
    z = gaussian_filter1d(ground, sigma, mode="nearest") + vehicle.reference_height_m
    position = np.column_stack([xy, z])
    rotation = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()
    velocity = np.gradient(position, STEP_S, axis=0)
    acceleration = gaussian_filter1d(np.gradient(velocity, STEP_S, axis=0), sigma / 2, axis=0, mode="nearest")
    delta = Rotation.from_matrix(np.einsum("nji,njk->nik", rotation[:-1], rotation[1:])).as_rotvec() / STEP_S
    body_rate = np.vstack([delta, delta[-1:]])
    return EgoTrajectory(time_s=t, s=s, position=position, rotation=rotation, velocity=velocity,
                         acceleration=acceleration, body_rate=body_rate,
                         speed=np.linalg.norm(velocity[:, :2], axis=1))


def specific_force_body(traj: EgoTrajectory, t: np.ndarray) -> np.ndarray:
    """What an ideal accelerometer aligned with the vehicle frame reads: R^T (a + g up)."""
    rot = traj.sample("rotation", t)
    a = traj.sample("acceleration", t) + np.array([0.0, 0.0, GRAVITY])
    return np.einsum("nji,nj->ni", rot, a)
