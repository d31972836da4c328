"""`roadlog export ros2 LOG... --out BAG`: roadlog logs as one ROS 2 bag (sqlite3 storage, written with `rosbags`) that
`roadlog import ros2` reads back.

Exported: each camera's frames (`/<camera>/image_raw/compressed` CompressedImage for jpeg/png, `/<camera>/image_raw`
Image for rgb8/bgr8/mono8) with a CameraInfo per frame (`/<camera>/camera_info`, from the recorded config), the Lidar's
scans as PointCloud2 (`/lidar/points`: x, y, z, intensity and `t`, ns after the stamp, in the Lidar frame; Ouster or
vendor packets decoded with the recorded metadata as the mapper decodes them, or the log's point clouds), GNSS fixes as
NavSatFix (`/gnss/fix`), the receiver's velocities as TwistWithCovarianceStamped (`/gnss/velocity`: the antenna's ENU
linear velocity, frame `gnss`, stamped as their epoch's fix; angular velocity unknown, covariance[21] = -1), IMU samples
as Imu (`/imu/data`, the Lidar's IMU on `/lidar/imu`), `/tf_static` (base_link -> every sensor frame from the config's
extrinsics) and the `pose` topic as nav_msgs Odometry (`/odom`) and `/tf`; without a `pose` topic, the daemon's live
pose (`vehicle/pose`, map -> vehicle) as `/tf` only (an Odometry would be imported as the drive's given trajectory,
where the original's reconstruction fuses it from the sensors). Every other topic is listed with its count on stderr,
never dropped silently.

Clock: ROS time is UTC. A message's receive time is its host time in UTC, and header.stamp its sensor time in UTC: a
sensor stamp already on UTC (GNSS, a PTP Lidar) as it is, any other put on the host clock as the mapper does
(sensor_time.fit_clock) and then on UTC, both through the log's time anchors (none: the host clock, said on stderr).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Writer
from scipy.spatial.transform import Rotation

from daemon.log_format.reader import not_a_log, read_log
from daemon.log_format.static_transforms import GNSS_FRAME, IMU_FRAME, LIDAR_FRAME, sensor_frames
from daemon.spine.config import CarConfig, ConfigError, reports_config_errors
from daemon.spine.messages import RAW_FORMAT_CHANNELS, CameraFrame, PointCloud, VehiclePose
from daemon.spine.topics import (
    GNSS_FIX,
    GNSS_VELOCITY,
    IMU,
    LIDAR_IMU,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    POSE,
    TIME_ANCHOR,
    VEHICLE_POSE,
)
from exporters import ros2_messages as ros
from mapping.inputs.lidar_ground import (
    LidarDecoding,
    ScanPoints,
    VendorDecoding,
    cloud_scan_points,
    configured_decoding,
    packet_scan_points,
    vendor_scan_points,
)
from mapping.localization.sensor_time import ClockMap, fit_clock
from mapping.offline.reconstruct_command import config_from_logs

BASE_FRAME = "base_link"  # the roadlog vehicle frame (the importer's default base frame)
CLOUD_TOPIC, ODOM_TOPIC = "/lidar/points", "/odom"
ROS_TOPICS = {GNSS_FIX: "/gnss/fix", GNSS_VELOCITY: "/gnss/velocity", IMU: "/imu/data", LIDAR_IMU: "/lidar/imu"}
FRAME_OF = {GNSS_FIX: GNSS_FRAME, GNSS_VELOCITY: GNSS_FRAME, IMU: IMU_FRAME, LIDAR_IMU: LIDAR_FRAME}
MSGTYPE_OF = {GNSS_FIX: ros.NAVSAT, GNSS_VELOCITY: ros.TWIST, IMU: ros.IMU_MSG, LIDAR_IMU: ros.IMU_MSG}


class UtcClock:
    """Host monotonic -> UTC through the log's time anchors ((mono, utc) pairs; utc - mono interpolated)."""

    def __init__(self, anchors: list[tuple[int, int]]):
        anchors = sorted(anchors)
        self.mono = np.array([a[0] for a in anchors], np.int64)
        self.diff = np.array([a[1] - a[0] for a in anchors], np.int64)

    def utc(self, host_ns: int) -> int:
        if not len(self.mono):
            return int(host_ns)
        m0, d0 = int(self.mono[0]), int(self.diff[0])
        return int(host_ns) + d0 + int(round(float(np.interp(float(host_ns - m0), (self.mono - m0).astype(float),
                                                             (self.diff - d0).astype(float)))))

    def stamp(self, clock: ClockMap, sensor_ns: int) -> int:
        """A sensor stamp in UTC."""
        if clock.kind == "utc":
            return int(sensor_ns)
        return self.utc(int(clock.to_host([sensor_ns])[0]))


def _survey(logs: list[Path]) -> tuple[dict[str, ClockMap], UtcClock, Counter]:
    """First pass: each topic's sensor clock (as the mapper fits it), the anchors' UTC clock, messages per topic."""
    times, anchors, counts = defaultdict(list), [], Counter()
    for r in read_log(logs):
        counts[r.topic] += 1
        if r.topic == TIME_ANCHOR:
            anchors.append((r.message.host_mono_ns, r.message.utc_ns))
        times[r.topic].append((r.message.sensor_time_ns, r.log_time_ns))
    clocks = {t: fit_clock([s for s, _ in v], [h for _, h in v], anchors) for t, v in times.items()}
    return clocks, UtcClock(anchors), counts


def _lidar_scans(records: Iterator, config: CarConfig, config_path: Path) -> Iterator[tuple[ScanPoints, int]]:
    """Each scan of the Lidar messages as decoded points, with the host time of its last message: a PointCloud
    is one scan, an Ouster's packets `packets_per_frame` to a scan (from the first), a vendor's by rotation period
    (each with the packet before it as its lead), exactly as lidar_ground groups them."""
    decoding, ouster, chunk, lead, period = None, None, [], None, None
    for r in records:
        m = r.message
        if isinstance(m, PointCloud):
            yield cloud_scan_points(m), r.log_time_ns
            continue
        if decoding is None:
            decoding = configured_decoding(config.sensors.lidar, config_path)
            if decoding is None:
                raise ConfigError("the recorded config's Lidar is a point-cloud Lidar but the log holds packets")
            ouster = None if isinstance(decoding, VendorDecoding) else LidarDecoding.of(decoding)
        if ouster is not None:
            chunk.append(r)
            if len(chunk) == decoding.packets_per_frame:
                yield packet_scan_points([bytes(p.message.data) for p in chunk], ouster), chunk[-1].log_time_ns
                chunk = []
            continue
        this = m.sensor_time_ns // decoding.rotation_period_ns
        if chunk and this != period:
            yield vendor_scan_points(lead, [p.message for p in chunk], decoding), chunk[-1].log_time_ns
            lead, chunk = chunk[-1].message, []
        chunk.append(r)
        period = this
    if chunk and ouster is not None:
        yield packet_scan_points([bytes(p.message.data) for p in chunk], ouster), chunk[-1].log_time_ns
    elif chunk:
        yield vendor_scan_points(lead, [p.message for p in chunk], decoding), chunk[-1].log_time_ns


def _cloud(scan: ScanPoints, clock: ClockMap, utc: UtcClock):
    """A scan as a PointCloud2 stamped with its first firing, each point's `t` after it (None: no points)."""
    if not len(scan.times_ns):
        return None
    start = int(scan.times_ns.min())
    offsets = (scan.times_ns - start)[scan.time_index]
    return ros.point_cloud(scan.xyz, scan.intensity, offsets.astype(np.uint32), utc.stamp(clock, start),
                           LIDAR_FRAME)


def export_bag(logs: list[Path], out: Path) -> tuple[dict[str, int], dict[str, str]]:
    """Write the bag; (messages per bag topic, {log topic: why not exported (count)})."""
    for log in logs:
        why = not_a_log(log) if log.exists() else f"{log}: no such log"
        if why:
            raise ConfigError(why)
    if out.exists():
        raise ConfigError(f"{out} exists (a bag is a new folder)")
    config, config_path = config_from_logs([str(p) for p in logs])
    clocks, utc, counts = _survey(logs)
    if not counts:
        raise ConfigError(f"{', '.join(map(str, logs))}: no messages")
    cameras = {f"camera/{c.name}": c for c in config.sensors.cameras}
    poses = POSE if counts[POSE] or not counts[VEHICLE_POSE] else VEHICLE_POSE  # the one source of /tf
    exported = set(cameras) | set(ROS_TOPICS) | {poses, LIDAR_PACKETS, LIDAR_POINTS}
    skipped = {t: f"not exported ({n})" for t, n in counts.items() if t not in exported and t != TIME_ANCHOR}
    if poses == POSE and counts[VEHICLE_POSE]:
        skipped[VEHICLE_POSE] = f"the `pose` topic gives /odom and /tf ({counts[VEHICLE_POSE]})"
    if TIME_ANCHOR in counts:
        skipped[TIME_ANCHOR] = f"used for the stamps' UTC clock, not exported ({counts[TIME_ANCHOR]})"
    work = out.with_name(out.name + ".partial")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    written, unusable = Counter(), Counter()
    try:
        first_utc = utc.utc(next(iter(read_log(logs))).log_time_ns)
        with Writer(work / out.name) as writer:
            bag = ros.BagWriter(writer)
            statics = [ros.transform(BASE_FRAME, name, e.matrix(), first_utc)
                       for name, e in sensor_frames(config).items()]
            bag.write("/tf_static", ros.TF, first_utc, ros.tf_message(statics))
            for topic in (t for t in ROS_TOPICS if counts[t]):  # the car's IMU before the Lidar's: imported first
                bag.connect(ROS_TOPICS[topic], MSGTYPE_OF[topic])
            written["/tf_static"] += 1
            for r in read_log(logs, topics=sorted(set(cameras) | set(ROS_TOPICS) | {poses})):
                for topic, msgtype, msg in _convert(r, cameras, clocks, utc):
                    if msg is None:
                        unusable[r.topic] += 1
                        continue
                    bag.write(topic, msgtype, utc.utc(r.log_time_ns), msg)
                    written[topic] += 1
            lidar_topic = LIDAR_POINTS if counts[LIDAR_POINTS] else LIDAR_PACKETS
            if counts[lidar_topic] and config.sensors.lidar is not None:
                for scan, host_ns in _lidar_scans(read_log(logs, topics=[lidar_topic]), config, config_path):
                    msg = _cloud(scan, clocks[lidar_topic], utc)
                    if msg is not None:
                        bag.write(CLOUD_TOPIC, ros.CLOUD, utc.utc(host_ns), msg)
                        written[CLOUD_TOPIC] += 1
            elif counts[lidar_topic]:
                skipped[lidar_topic] = f"no Lidar in the recorded config, not exported ({counts[lidar_topic]})"
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    (work / out.name).replace(out)
    work.rmdir()
    for topic, n in unusable.items():
        skipped[topic] = f"frames in a format a ROS image cannot hold (h264/h265), not exported ({n})"
    if not len(utc.mono):
        skipped[TIME_ANCHOR] = "none in the log: stamps are on the host monotonic clock, not UTC"
    return dict(written), skipped


def _convert(r, cameras: dict, clocks: dict[str, ClockMap], utc: UtcClock) -> list[tuple[str, str, object]]:
    m, clock = r.message, clocks[r.topic]
    if isinstance(m, CameraFrame):
        cam = cameras[r.topic]
        stamp = utc.stamp(clock, m.sensor_time_ns)
        info = (f"/{cam.name}/camera_info", ros.INFO, ros.camera_info(cam, stamp, cam.name))
        if m.format in ("jpeg", "png"):
            return [(f"/{cam.name}/image_raw/compressed", ros.COMPRESSED, ros.compressed_image(m, stamp, cam.name)),
                    info]
        if m.format in RAW_FORMAT_CHANNELS:
            return [(f"/{cam.name}/image_raw", ros.IMAGE, ros.raw_image(m, stamp, cam.name)), info]
        return [("", "", None)]
    if isinstance(m, VehiclePose):
        stamp = utc.stamp(clock, m.sensor_time_ns)
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat(m.orientation_xyzw).as_matrix()
        pose[:3, 3] = m.position_m
        tf = ("/tf", ros.TF, ros.tf_message([ros.transform(m.frame_id, BASE_FRAME, pose, stamp)]))
        if r.topic == VEHICLE_POSE:
            return [tf]
        return [(ODOM_TOPIC, ros.ODOMETRY, ros.odometry(m.position_m, m.orientation_xyzw, stamp, m.frame_id,
                                                        BASE_FRAME)), tf]
    if r.topic == GNSS_VELOCITY:  # on its fix's clock: the same stamp as the NavSatFix of its epoch
        stamp = utc.stamp(clocks.get(GNSS_FIX, clock), m.sensor_time_ns)
        return [(ROS_TOPICS[r.topic], ros.TWIST, ros.gnss_velocity(m, stamp, FRAME_OF[r.topic]))]
    stamp = utc.stamp(clock, m.sensor_time_ns)
    if r.topic == GNSS_FIX:
        return [(ROS_TOPICS[r.topic], ros.NAVSAT, ros.nav_sat_fix(m, stamp, FRAME_OF[r.topic]))]
    return [(ROS_TOPICS[r.topic], ros.IMU_MSG, ros.imu(m, stamp, FRAME_OF[r.topic]))]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", type=Path, help="the roadlog MCAP log(s) of one drive")
    parser.add_argument("--out", required=True, type=Path, help="the bag folder to write (must not exist)")


@reports_config_errors
def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    written, skipped = export_bag(args.logs, args.out)
    for topic, why in skipped.items():
        print(f"not exported {topic}: {why}", file=sys.stderr)
    print(json.dumps({"bag": str(args.out), "messages": written, "not_exported": skipped,
                      "wall_s": round(time.perf_counter() - started, 3)}))
    return 0
