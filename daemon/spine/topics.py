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
    GnssVelocity,
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
    # how far before its publish a message's host stamp may lie: a product made from other topics (a viewing cloud,
    # a fused pose) is stamped at the time it shows, published once made; the recorder waits that long to order it
    stamp_lag_s: float = 0.0


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


# For viewing, beside the lossless record (recorder.point_cloud_view_hz, recorder.pose_hz): every few Lidar scans
# decoded into points by the `lidar_view` process (PointCloud on `lidar/view`, foxglove.PointCloud in the frame of
# the Lidar, stamped on the host clock as the camera frames are); the mapper never reads it (it decodes the packets).
# The vehicle pose fused live by the `vehicle_pose` process (VehiclePose in MAP_FRAME on `vehicle/pose`, logged as
# foxglove.PoseInFrame and again on the log-only `tf` channel as a foxglove.FrameTransform MAP_FRAME -> vehicle).
LIDAR_VIEW = "lidar/view"
VEHICLE_POSE = "vehicle/pose"
TF = "tf"
MAP_FRAME = "map"  # local ENU at the run's first GNSS fix (east, north, up; metres)
LIDAR_VIEW_PROCESS = "lidar_view"
VEHICLE_POSE_PROCESS = "vehicle_pose"
VIEW_STAMP_LAG_S = 1.0  # a viewing cloud is published once its scan has been received and decoded
POSE_STAMP_LAG_S = 3.0  # a pose is published once the fusion has run over the data after it (vehicle_pose)
POINT_CLOUD_BYTES = 16 * MB  # the largest input cloud: 128 beams x 2048 columns x 2 returns of 20 B, and room
VIEW_CLOUD_BYTES = 8 * MB  # the largest viewing cloud: 400,000 points with a return (a 128-beam scan of 2048)


def views_lidar(config: CarConfig) -> bool:
    """Whether the car logs viewing clouds: a Lidar that sends packets, and recorder.point_cloud_view_hz > 0 (a
    point-cloud Lidar's scans are logged decoded already)."""
    lidar = config.sensors.lidar
    return lidar is not None and not lidar.point_clouds and config.recorder.point_cloud_view_hz > 0


def fuses_pose(config: CarConfig) -> bool:
    """Whether the car publishes its live pose: GNSS (with its IMU) and recorder.pose_hz > 0."""
    return config.sensors.gnss is not None and config.recorder.pose_hz > 0


def camera_process(camera: str) -> str:
    return f"camera_{camera}"


def health_topic(process: str) -> str:
    return f"health/{process}"


LIDAR_PACKETS = "lidar/packets"
LIDAR_IMU = "lidar/imu"  # the Lidar's own IMU (Ouster: UDP udp_port_imu)
LIDAR_POINTS = "lidar/points"  # a point-cloud Lidar's scans, decoded (instead of lidar/packets and lidar/imu)
GNSS_FIX = "gnss/fix"
GNSS_VELOCITY = "gnss/velocity"  # the receiver's velocity of its antenna (u-blox NAV-PVT, NAV-PVAT; NMEA RMC, VTG)
IMU = "imu"
CAN_FRAMES = "can/frames"
WHEEL_SPEEDS = "wheel_speeds"
TIME_ANCHOR = "time_anchor"

GNSS_TOPIC_BY_TYPE = {GnssFix: GNSS_FIX, GnssVelocity: GNSS_VELOCITY, ImuSample: IMU}  # what a GNSS receiver gives
FUSION_TOPICS = (GNSS_FIX, GNSS_VELOCITY, IMU, WHEEL_SPEEDS)  # what the pose fusion takes (mapping.inputs.drive_inputs)

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
        # ring holds ~4 s of packets; the largest, 2048 columns with two returns, is 10.5 MB (20 B a point)
        topics.append(Topic(LIDAR_POINTS, PointCloud, sensors.lidar.rate_hz, 128 * MB, True, "lidar",
                            POINT_CLOUD_BYTES))
    elif sensors.lidar is not None:
        packets_per_s = sensors.lidar.columns_per_frame / 16 * sensors.lidar.rate_hz
        topics.append(Topic(LIDAR_PACKETS, LidarPacket, packets_per_s, 128 * MB, True, "lidar", UDP_DATAGRAM_BYTES))
        topics.append(Topic(LIDAR_IMU, ImuSample, 100.0, 4 * MB, True, "lidar"))
    if sensors.gnss is not None:
        topics.append(Topic(GNSS_FIX, GnssFix, sensors.gnss.rate_hz, 4 * MB, True, "gnss"))
        topics.append(Topic(GNSS_VELOCITY, GnssVelocity, sensors.gnss.rate_hz, 4 * MB, True, "gnss"))
        topics.append(Topic(IMU, ImuSample, sensors.gnss.imu_rate_hz, 8 * MB, True, "gnss"))
    if sensors.can is not None:
        topics.append(Topic(CAN_FRAMES, CanFrame, 2000.0, 16 * MB, True, "can"))
        topics.append(Topic(WHEEL_SPEEDS, WheelSpeeds, 50.0, 4 * MB, True, "can"))
    topics.append(Topic(TIME_ANCHOR, TimeAnchor, 1.0, 1 * MB, True, "recorder"))
    viewers = []
    if views_lidar(config):
        topics.append(Topic(LIDAR_VIEW, PointCloud, config.recorder.point_cloud_view_hz, 4 * VIEW_CLOUD_BYTES, True,
                            LIDAR_VIEW_PROCESS, VIEW_CLOUD_BYTES, VIEW_STAMP_LAG_S))
        viewers.append(LIDAR_VIEW_PROCESS)
    if fuses_pose(config):
        topics.append(Topic(VEHICLE_POSE, VehiclePose, config.recorder.pose_hz, 1 * MB, True, VEHICLE_POSE_PROCESS,
                            stamp_lag_s=POSE_STAMP_LAG_S))
        viewers.append(VEHICLE_POSE_PROCESS)
    for process in (*HEALTH_PROCESSES, *viewers):
        topics.append(Topic(health_topic(process), DriverHealth, 1.0, 1 * MB, True, process))
    table = {t.name: t for t in topics}
    unknown = sorted(set(config.bus.ring_bytes) - set(table))
    if unknown:
        raise ConfigError(f"bus.ring_bytes names unknown topics {', '.join(map(repr, unknown))} "
                          f"(known: {', '.join(sorted(table))})")
    for name, size in config.bus.ring_bytes.items():
        table[name] = dataclasses.replace(table[name], ring_bytes=size)
    return table
