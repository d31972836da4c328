"""The simulated car's CAN bus: wheel speeds and yaw rate from the true motion (with sensor noise), encoded
into frames by the car's DBC through drivers/can/wheel_speed_codec.py."""

from __future__ import annotations

import can
import numpy as np
from cantools.database import Database

from daemon.spine.config import CanSignals, VehicleConfig
from drivers.can.wheel_speed_codec import encode_wheel_speeds
from sim.world.ego_trajectory import EgoTrajectory

RATE_HZ = 50.0
SPEED_NOISE = 0.02  # m/s
YAW_NOISE = 0.002  # rad/s


def wheel_speeds(ego: EgoTrajectory, vehicle: VehicleConfig, true_s: np.ndarray, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
    """((N, 4) fl, fr, rl, rr ground speeds of the wheels in m/s, (N,) yaw rate rad/s), noisy.

    The reference point is the middle of the rear axle; a wheel's speed is the horizontal speed of its
    contact point."""
    rot = ego.sample("rotation", true_s)
    v_body = np.einsum("nji,nj->ni", rot, ego.sample("velocity", true_s))
    w = ego.sample("body_rate", true_s)
    half = vehicle.track_width_m / 2
    out = []
    for x, y in ((vehicle.wheel_base_m, half), (vehicle.wheel_base_m, -half), (0.0, half), (0.0, -half)):
        vx = v_body[:, 0] - w[:, 2] * y
        vy = v_body[:, 1] + w[:, 2] * x
        out.append(np.hypot(vx, vy))
    speeds = np.column_stack(out) + rng.normal(0, SPEED_NOISE, (len(true_s), 4))
    return speeds, w[:, 2] + rng.normal(0, YAW_NOISE, len(true_s))


def can_messages(db: Database, signals: CanSignals, speeds: np.ndarray, yaw: np.ndarray) -> list[list[can.Message]]:
    """The frames of each sample (yaw frame first), rolling counters running on."""
    return [encode_wheel_speeds(db, signals, *map(float, speeds[i]), float(yaw[i]), counter=i)
            for i in range(len(yaw))]
