"""Every message that crosses a process boundary or goes to disk, defined once as a dataclass.

Each message starts with the same three fields: `seq` (per-topic sequence number, set by the bus
publisher), `sensor_time_ns` (the sensor's own clock) and `host_mono_ns` (host CLOCK_MONOTONIC at
publish). Wall-clock time comes from the `TimeAnchor` messages (a monotonic/UTC pair once a second).
A message may carry one bulk `data` field (bytes); the bus moves it without copying.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

# A sensor stamp within this of its host arrival time is on the host's own monotonic clock (an OAK camera,
# the time anchors): mapping.localization.sensor_time takes it as it is, and a replay moves it with the host times.
HOST_CLOCK_WITHIN_NS = 1_000_000_000

Vec3 = tuple[float, float, float]

# The raw pixel formats a CameraFrame may carry, with their channels per pixel (8 bits each); every other
# format is an encoded bitstream (jpeg, png, h264, h265).
RAW_FORMAT_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1}


@dataclass(slots=True)
class CameraFrame:
    """One camera image: encoded bytes (jpeg, h264, h265) or raw pixels (rgb8, bgr8, mono8)."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    camera: str = ""
    format: str = "jpeg"
    width: int = 0  # raw formats only; 0 for encoded frames (the bitstream carries the size)
    height: int = 0
    data: bytes = b""


@dataclass(slots=True)
class SemanticMask:
    """Per-pixel class ids (daemon.spine.semantic_classes) for one camera frame, PNG-encoded mono8."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    camera: str = ""
    format: str = "png"
    data: bytes = b""


@dataclass(slots=True)
class LidarPacket:
    """One raw Lidar UDP datagram, as received."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    sensor: str = "lidar"
    data: bytes = b""


@dataclass(slots=True)
class PointCloud:
    """One Lidar scan already decoded into points (an imported dataset, another system's driver), whatever the vendor:
    `data` holds packed little-endian float32 records (x, y, z, intensity, time_s), one per point, in the Lidar
    frame (x forward, y left, z up, metres); time_s is the point's firing time in seconds after `sensor_time_ns`
    (the scan's start on the sensor clock). Packed and unpacked by daemon.spine.point_cloud_codec."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    sensor: str = "lidar"
    data: bytes = b""


@dataclass(slots=True)
class GnssFix:
    """A position fix (WGS84) with its covariance in local east/north/up metres squared (row-major 3x3)."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    latitude_deg: float = 0.0
    longitude_deg: float = 0.0
    altitude_m: float = 0.0
    position_covariance: tuple[float, ...] = (0.0,) * 9
    covariance_type: int = 0  # as foxglove.LocationFix: 0 unknown, 1 approximated, 2 diagonal, 3 known


@dataclass(slots=True)
class GnssVelocity:
    """The receiver's velocity of its antenna, east/north/up m/s, with its covariance in (m/s)^2 (row-major 3x3;
    covariance_type as GnssFix's: 0 unknown, 1 approximated (NMEA: no accuracy given, the vertical unknown and given a
    huge variance), 2 diagonal). `sensor_time_ns` is the fix's of the same epoch."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    velocity_enu_mps: Vec3 = (0.0, 0.0, 0.0)
    velocity_covariance: tuple[float, ...] = (0.0,) * 9
    covariance_type: int = 0


@dataclass(slots=True)
class ImuSample:
    """Specific force (m/s^2) and angular rate (rad/s) in the IMU frame."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    accel_mps2: Vec3 = (0.0, 0.0, 0.0)
    gyro_rps: Vec3 = (0.0, 0.0, 0.0)


@dataclass(slots=True)
class WheelSpeeds:
    """Four wheel speeds (m/s) and the yaw rate (rad/s, NaN when the car does not send one)."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    front_left_mps: float = 0.0
    front_right_mps: float = 0.0
    rear_left_mps: float = 0.0
    rear_right_mps: float = 0.0
    yaw_rate_rps: float = float("nan")


@dataclass(slots=True)
class CanFrame:
    """One raw CAN frame (error frames included, flagged)."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    arbitration_id: int = 0
    is_extended_id: bool = False
    is_error_frame: bool = False
    is_remote_frame: bool = False
    channel: str = ""
    data: bytes = b""


@dataclass(slots=True)
class VehiclePose:
    """The fused pose of the vehicle reference frame in the local ENU frame (quaternion x, y, z, w)."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    frame_id: str = "enu"
    position_m: Vec3 = (0.0, 0.0, 0.0)
    orientation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)


@dataclass(slots=True)
class DriverHealth:
    """A process's health, published once a second."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    process: str = ""
    state: str = "ok"  # ok | degraded | error | starting (loading: alive, not yet up)
    rate_hz: float = 0.0
    last_message_age_s: float = float("inf")
    received: int = 0
    published: int = 0
    dropped: int = 0
    rejected: int = 0
    errors: int = 0
    sequence_gaps: int = 0
    detail: str = ""


@dataclass(slots=True)
class TimeAnchor:
    """A host monotonic / UTC time pair: converts any host_mono_ns in the log to wall-clock time."""

    seq: int = 0
    sensor_time_ns: int = 0
    host_mono_ns: int = 0
    utc_ns: int = 0


MESSAGE_TYPES: tuple[type, ...] = (
    CameraFrame,
    SemanticMask,
    LidarPacket,
    PointCloud,
    GnssFix,
    GnssVelocity,
    ImuSample,
    WheelSpeeds,
    CanFrame,
    VehiclePose,
    DriverHealth,
    TimeAnchor,
)
MESSAGE_TYPE_BY_NAME: dict[str, type] = {t.__name__: t for t in MESSAGE_TYPES}


def bulk_field(message_type: type) -> str | None:
    """The name of the message's bulk bytes field, if it has one."""
    names = {f.name for f in dataclasses.fields(message_type)}
    return "data" if "data" in names else None


__all__ = [t.__name__ for t in MESSAGE_TYPES] + ["MESSAGE_TYPES", "MESSAGE_TYPE_BY_NAME", "bulk_field"]
