"""The topic table: the only place a topic is declared (name, message type, rate, ring size, logged).

Per-camera and per-process topics are declared once here as templates and expanded from the car's
config by `topic_table`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from daemon.spine.config import CarConfig, ConfigError
from daemon.spine.messages import (
    CameraFrame,
    CanFrame,
    DriverHealth,
    GnssFix,
    ImuSample,
    LidarPacket,
    PointCloud,
    SemanticMask,
    TimeAnchor,
    VehiclePose,
    WheelSpeeds,
)

MB = 1024 * 1024
SMALL_MESSAGE_BYTES = 64 * 1024  # the largest of the small messages (IMU, fixes, CAN, health with its JSON detail)
UDP_DATAGRAM_BYTES = 65_535  # a Lidar packet is one datagram


@dataclass(frozen=True)
class Topic:
    name: str
    message_type: type
    rate_hz: float
    ring_bytes: int
    logged: bool = True
    source: str = ""  # the process that writes it (a process table name, or "supervisor")
    max_message_bytes: int = SMALL_MESSAGE_BYTES  # the largest payload it carries (a ring must hold a few)


def camera_topic(camera: str) -> str:
    return f"camera/{camera}"


def mask_topic(camera: str) -> str:
    return f"mask/{camera}"


def calibration_topic(camera: str) -> str:
    """Log-only channel (foxglove.CameraCalibration) written once at the start of every log file."""
    return f"calibration/{camera}"


def mask_colour_topic(camera: str) -> str:
    """Log-only channel (foxglove.CompressedImage): each mask of `mask/<camera>` as a paletted PNG, for viewing."""
    return f"mask_colour/{camera}"


# Log-only channel (foxglove.FrameTransforms) written once at the start of every log file: the vehicle frame to each
# sensor's frame (the images', the point clouds', the GNSS fixes' frame_id), from the config's extrinsics.
TF_STATIC = "tf_static"
VEHICLE_FRAME = "vehicle"

# Log-only channel (foxglove.PoseInFrame): vehicle poses that came with a log from elsewhere (an importer's ground
# truth, another system's localisation). No roadlog process publishes it, so it is not a bus topic; `roadlog
# reconstruct` uses a log's poses instead of fusing its GNSS, IMU and wheel speeds.
POSE = "pose"
LOG_ONLY_CHANNELS: dict[str, type] = {POSE: VehiclePose}  # channels a log may carry beside the bus topics


def camera_process(camera: str) -> str:
    return f"camera_{camera}"


def health_topic(process: str) -> str:
    return f"health/{process}"


LIDAR_PACKETS = "lidar/packets"
LIDAR_IMU = "lidar/imu"  # the Lidar's own IMU (Ouster: UDP udp_port_imu)
LIDAR_POINTS = "lidar/points"  # a point-cloud Lidar's scans, decoded (instead of lidar/packets and lidar/imu)
GNSS_FIX = "gnss/fix"
IMU = "imu"
CAN_FRAMES = "can/frames"
WHEEL_SPEEDS = "wheel_speeds"
TIME_ANCHOR = "time_anchor"

# Processes that publish a health topic besides one camera driver per camera ("camera_<name>").
HEALTH_PROCESSES = ("lidar", "gnss", "can", "recorder", "mapper", "replay", "supervisor", "status")


def topic_table(config: CarConfig) -> dict[str, Topic]:
    """Every topic of this car, keyed by name."""
    sensors = config.sensors
    topics: list[Topic] = []
    for cam in sensors.cameras:
        raw_bytes = cam.width * cam.height * 3
        ring = max(64 * MB, 4 * raw_bytes + MB)
        process = camera_process(cam.name)
        topics.append(Topic(camera_topic(cam.name), CameraFrame, cam.rate_hz, ring, True, process, raw_bytes))
        topics.append(Topic(mask_topic(cam.name), SemanticMask, cam.rate_hz, max(16 * MB, 2 * raw_bytes), True,
                            process, cam.width * cam.height + SMALL_MESSAGE_BYTES))  # a PNG of class ids, worst case
        topics.append(Topic(health_topic(process), DriverHealth, 1.0, 1 * MB, True, process))
    if sensors.lidar is not None and sensors.lidar.point_clouds:
        # a 128-beam scan of 1024 columns is ~2.6 MB of points: the ring holds ~5 s of them at 10 Hz, as the packet
        # ring holds ~4 s of packets
        topics.append(Topic(LIDAR_POINTS, PointCloud, sensors.lidar.rate_hz, 128 * MB, True, "lidar"))
    elif sensors.lidar is not None:
        packets_per_s = sensors.lidar.columns_per_frame / 16 * sensors.lidar.rate_hz
        topics.append(Topic(LIDAR_PACKETS, LidarPacket, packets_per_s, 128 * MB, True, "lidar", UDP_DATAGRAM_BYTES))
        topics.append(Topic(LIDAR_IMU, ImuSample, 100.0, 4 * MB, True, "lidar"))
    if sensors.gnss is not None:
        topics.append(Topic(GNSS_FIX, GnssFix, sensors.gnss.rate_hz, 4 * MB, True, "gnss"))
        topics.append(Topic(IMU, ImuSample, sensors.gnss.imu_rate_hz, 8 * MB, True, "gnss"))
    if sensors.can is not None:
        topics.append(Topic(CAN_FRAMES, CanFrame, 2000.0, 16 * MB, True, "can"))
        topics.append(Topic(WHEEL_SPEEDS, WheelSpeeds, 50.0, 4 * MB, True, "can"))
    topics.append(Topic(TIME_ANCHOR, TimeAnchor, 1.0, 1 * MB, True, "recorder"))
    for process in HEALTH_PROCESSES:
        topics.append(Topic(health_topic(process), DriverHealth, 1.0, 1 * MB, True, process))
    table = {t.name: t for t in topics}
    unknown = sorted(set(config.bus.ring_bytes) - set(table))
    if unknown:
        raise ConfigError(f"bus.ring_bytes names unknown topics {', '.join(map(repr, unknown))} "
                          f"(known: {', '.join(sorted(table))})")
    for name, size in config.bus.ring_bytes.items():
        table[name] = dataclasses.replace(table[name], ring_bytes=size)
    return table
