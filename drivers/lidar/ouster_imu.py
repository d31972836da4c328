"""Ouster IMU packets (UDP `udp_port_imu`, 100 Hz) into ImuSample messages.

Only the LEGACY IMU profile is decoded: 48 bytes, little-endian: the packet's system time, the
accelerometer's and the gyroscope's read times (uint64 ns, the sensor's clock: the one its Lidar packets
are stamped with), then linear acceleration x, y, z (float32, g) and angular velocity x, y, z (float32,
deg/s) in the sensor's IMU frame (`imu_to_sensor_transform` in the metadata). A sample's time is its
accelerometer read time (the gyroscope's follows within ~0.2 ms). Firmware 3.1's ACCEL32_GYRO32_NMEA
profile (eight measurements a packet) is not decoded: the driver reports it and records the Lidar only.
`encode_imu_packet` is the inverse, for the simulator.
"""

from __future__ import annotations

import math
import struct

from daemon.spine.messages import ImuSample

LEGACY_IMU = struct.Struct("<QQQ6f")
LEGACY_IMU_BYTES = LEGACY_IMU.size  # 48
STANDARD_GRAVITY_MPS2 = 9.80665


def imu_profile_supported(profile: str) -> bool:
    return profile == "LEGACY"


def decode_imu_packet(payload: bytes | memoryview, host_mono_ns: int, size: int | None = None) -> ImuSample:
    """One LEGACY IMU packet; ValueError for one of another size or with a value that is not finite. `size`:
    the datagram's real length when `payload` may be cut short (a receive buffer's row)."""
    size = len(payload) if size is None else size
    if size != LEGACY_IMU_BYTES:
        raise ValueError(f"IMU datagram of {size} B (a LEGACY IMU packet is {LEGACY_IMU_BYTES} B)")
    _, accel_ns, _, ax, ay, az, gx, gy, gz = LEGACY_IMU.unpack(payload)
    values = (ax, ay, az, gx, gy, gz)
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"IMU packet with a value that is not a number: {values}")
    g, rad = STANDARD_GRAVITY_MPS2, math.pi / 180.0
    return ImuSample(sensor_time_ns=accel_ns, host_mono_ns=host_mono_ns,
                     accel_mps2=(ax * g, ay * g, az * g), gyro_rps=(gx * rad, gy * rad, gz * rad))


def encode_imu_packet(sample: ImuSample, gyro_after_ns: int = 200_000) -> bytes:
    """The LEGACY packet the sensor would send for `sample` (for the simulator; the gyroscope read
    `gyro_after_ns` after the accelerometer, the packet stamped at the accelerometer read)."""
    g, deg = STANDARD_GRAVITY_MPS2, 180.0 / math.pi
    t = int(sample.sensor_time_ns)
    return LEGACY_IMU.pack(t, t, t + gyro_after_ns, *(v / g for v in sample.accel_mps2),
                           *(v * deg for v in sample.gyro_rps))
