"""The simulated IMU inside the GNSS receiver: specific force and angular rate of the car in the IMU's axes
at 100 Hz with noise and bias, and the u-blox UBX ESF-RAW messages that carry them."""

from __future__ import annotations

import struct

import numpy as np

from drivers.gnss.stream_framer import ubx_checksum
from sim.world.ego_trajectory import EgoTrajectory, specific_force_body

ACCEL_NOISE = 0.03  # m/s^2
ACCEL_BIAS = 0.02
GYRO_NOISE = 0.003  # rad/s
GYRO_BIAS = 0.001
ACCEL_LSB = 2.0**-10  # m/s^2 per ESF-RAW count
GYRO_LSB = np.radians(2.0**-12)  # rad/s per count
GYRO_TYPES = (14, 13, 5)  # x, y, z
ACCEL_TYPES = (16, 17, 18)


def imu_readings(ego: EgoTrajectory, imu_to_vehicle: np.ndarray, true_s: np.ndarray, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(specific force (N, 3) m/s^2, angular rate (N, 3) rad/s) in the IMU frame, noisy and biased."""
    rot_vi = imu_to_vehicle[:3, :3]
    n = len(true_s)
    force = specific_force_body(ego, true_s) @ rot_vi
    rate = ego.sample("body_rate", true_s) @ rot_vi
    force += rng.normal(0, ACCEL_BIAS, 3) + rng.normal(0, ACCEL_NOISE, (n, 3))
    rate += rng.normal(0, GYRO_BIAS, 3) + rng.normal(0, GYRO_NOISE, (n, 3))
    return force, rate


def esf_raw_bytes(force: np.ndarray, rate: np.ndarray, tick: int) -> bytes:
    """One UBX ESF-RAW frame with the six axes of one sample, all stamped with a 24-bit sensor tick."""
    payload = bytearray(4)
    tag = tick & 0xFFFFFF
    for dtype, value in zip(GYRO_TYPES + ACCEL_TYPES, np.r_[rate / GYRO_LSB, force / ACCEL_LSB], strict=True):
        count = int(np.clip(round(float(value)), -(1 << 23), (1 << 23) - 1)) & 0xFFFFFF
        payload += struct.pack("<II", (dtype << 24) | count, tag)
    body = b"\x10\x03" + struct.pack("<H", len(payload)) + bytes(payload)
    return b"\xb5\x62" + body + ubx_checksum(body)
