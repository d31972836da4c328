"""`roadlog import ros2 BAG --out LOG.mcap`: a ROS 2 bag (sqlite3 or MCAP storage, read with `rosbags`) as a roadlog
log that `roadlog reconstruct LOG` maps with nothing else.

Imported: sensor_msgs Image (rgb8, bgr8, mono8) and CompressedImage (jpeg, png) as camera frames, each camera's
CameraInfo as its intrinsics (a camera without one is skipped: a map needs them), NavSatFix and Imu as GNSS fixes and
IMU samples, a TwistWithCovarianceStamped in the NavSatFix's frame as the receiver's ENU velocity (`gnss/velocity`, as
the u-blox ROS driver and `roadlog export ros2` write it; another frame's twist is not a GNSS velocity), PointCloud2 as
the scans of a point-cloud Lidar (x, y, z, intensity, and a per-point `time`, `t` or `timestamp` field where the driver
gives one), nav_msgs Odometry as the `pose` topic (the base frame in the odometry's frame), tf_static (and /tf between
sensor frames) as the sensors' extrinsics in the base frame (`--base-frame`, default: the Odometry's child frame, else
base_link). Every other topic, and every message that cannot be used, is listed with its count and reason on stderr and
in the printed summary, never dropped silently. Stamps: header.stamp is the sensor time, the bag's receive time the host
time (ROS time: UTC, so time anchors pair it with itself).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from daemon.spine.config import POINT_CLOUD_LIDAR, reports_config_errors
from daemon.spine.messages import TimeAnchor
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU, LIDAR_POINTS, POSE, TIME_ANCHOR, camera_topic
from importers import ros2_messages as ros
from importers.imported_log import ImportSummary, imported_log, vehicle_pose
from importers.kitti_files import DatasetError, extrinsics, imported_car_config, recorded_camera

IMAGE, COMPRESSED, INFO = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
NAVSAT, IMU_MSG, ODOMETRY, TF = "sensor_msgs/msg/NavSatFix", "sensor_msgs/msg/Imu", "nav_msgs/msg/Odometry", \
    "tf2_msgs/msg/TFMessage"
CLOUD, TWIST = "sensor_msgs/msg/PointCloud2", "geometry_msgs/msg/TwistWithCovarianceStamped"
IMPORTED_TYPES = {IMAGE, COMPRESSED, INFO, NAVSAT, IMU_MSG, ODOMETRY, TF, CLOUD, TWIST}


def _open(bag: Path) -> AnyReader:
    if not bag.exists():
        raise DatasetError(f"{bag}: no such bag")
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises its own error per storage and version
        raise DatasetError(f"{bag}: not a readable ROS 2 bag ({type(exc).__name__}: {exc})") from None
    return reader


def _survey(reader: AnyReader) -> tuple[dict[str, ros.CameraInfo], ros.FrameTree, dict[str, str]]:
    """First pass: each camera's CameraInfo, the static frame tree, and why each camera info was refused."""
    infos, refused, tree = {}, {}, ros.FrameTree()
    wanted = [c for c in reader.connections if c.msgtype in (INFO, TF)]
    for conn, _, raw in reader.messages(connections=wanted):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.msgtype == TF:
            for transform in msg.transforms:
                tree.add(transform)
            continue
        name = ros.camera_name(conn.topic)
        if name not in infos:
            info, why = ros.camera_info(msg)
            if info is None:
                refused[name] = why
            else:
                infos[name] = info
                refused.pop(name, None)
    return infos, tree, refused


def _rate(times: list[int]) -> float:
    return float((len(times) - 1) / ((times[-1] - times[0]) * 1e-9)) if len(times) > 1 and times[-1] > times[0] \
        else 10.0


def import_bag(bag: Path, out: Path, *, base_frame: str | None = None, reference_height_m: float = 0.0
               ) -> tuple[ImportSummary, dict[str, str]]:
    """The log, and what was skipped: {topic: "msgtype: reason (count)"}."""
    started = time.perf_counter()
    reader = _open(bag)
    try:
        infos, tree, refused = _survey(reader)
        odometry = [c for c in reader.connections if c.msgtype == ODOMETRY]
        skipped: dict[str, Counter] = defaultdict(Counter)
        for conn in reader.connections:
            if conn.msgtype not in IMPORTED_TYPES:
                skipped[conn.topic][f"{conn.msgtype}: not an imported type"] += conn.msgcount
        first_odometry = next(reader.messages(connections=odometry[:1]), None) if odometry else None  # none: all
        child = reader.deserialize(first_odometry[2], ODOMETRY).child_frame_id if first_odometry else ""
        base = (base_frame or child or "base_link").strip("/")
        image_conns = [c for c in reader.connections if c.msgtype in (IMAGE, COMPRESSED)]
        cameras, camera_of = [], {}
        for conn in image_conns:
            name = ros.camera_name(conn.topic)
            info = infos.get(name)
            if info is None:
                skipped[conn.topic][f"{conn.msgtype}: no usable CameraInfo for camera {name!r} "
                                    f"({refused.get(name, 'none in the bag')})"] += conn.msgcount
                continue
            if name in camera_of.values():
                skipped[conn.topic][f"{conn.msgtype}: camera {name!r} already imported from another topic"] += \
                    conn.msgcount
                continue
            t_base_camera = tree.lookup(base, info.frame_id)
            if t_base_camera is None:
                skipped[conn.topic][f"{conn.msgtype}: no transform from {base!r} to {info.frame_id!r}"] += \
                    conn.msgcount
                continue
            camera_of[conn.topic] = name
            times = [t for _, t, _ in reader.messages(connections=[conn])]
            encoding = "raw"
            if conn.msgtype == COMPRESSED:
                first = reader.deserialize(next(reader.messages(connections=[conn]))[2], COMPRESSED)
                encoding = "png" if "png" in first.format.lower() else "jpeg"
            cameras.append(recorded_camera(name, info.width, info.height, info.k, t_base_camera,
                                           round(_rate(times), 3), encoding) | {"distortion": list(info.distortion)})
        if not cameras:
            raise DatasetError(f"{bag}: no camera with images and a CameraInfo (skipped: "
                               f"{json.dumps({t: list(c) for t, c in skipped.items()})})")
        sensors = {}
        navsat = [c for c in reader.connections if c.msgtype == NAVSAT]
        imus = [c for c in reader.connections if c.msgtype == IMU_MSG]
        if navsat or imus:
            sensors["gnss"] = _gnss_config(reader, navsat[:1], imus[:1], tree, base)
        clouds = [c for c in reader.connections if c.msgtype == CLOUD]
        if clouds:
            first = reader.deserialize(next(reader.messages(connections=clouds[:1]))[2], CLOUD)
            t_base_lidar = tree.lookup(base, first.header.frame_id)
            if t_base_lidar is None:
                for conn in clouds:
                    skipped[conn.topic][f"{CLOUD}: no transform from {base!r} to {first.header.frame_id!r}"] += \
                        conn.msgcount
                clouds = []
            else:
                sensors["lidar"] = {"model": POINT_CLOUD_LIDAR, "extrinsics": extrinsics(t_base_lidar)}
        velocity = _gnss_velocity_connections(reader, navsat[:1], skipped)
        for extra in navsat[1:] + imus[1:] + odometry[1:] + clouds[1:] + velocity[1:]:
            skipped[extra.topic][f"{extra.msgtype}: a second {extra.msgtype.rsplit('/', 1)[-1]} topic "
                                 f"(the first is imported)"] += extra.msgcount
        config = imported_car_config(f"ros2-{bag.name}", cameras, reference_height_m, bag, **sensors)
        metadata = {"source": f"ROS 2 bag {bag.resolve()}", "import": json.dumps({"base_frame": base})}
        chosen = image_conns + navsat[:1] + velocity[:1] + imus[:1] + odometry[:1] + clouds[:1]
        with imported_log(out, config, metadata) as writer:
            seq, frame_times, next_anchor = Counter(), [], None
            for conn, host_ns, raw in reader.messages(connections=chosen):
                if conn.topic not in camera_of and conn.msgtype in (IMAGE, COMPRESSED):
                    continue
                if next_anchor is None or host_ns >= next_anchor:
                    writer.write(TIME_ANCHOR, TimeAnchor(seq=seq[TIME_ANCHOR], sensor_time_ns=host_ns,
                                                         host_mono_ns=host_ns, utc_ns=host_ns))
                    seq[TIME_ANCHOR] += 1
                    next_anchor = host_ns + 1_000_000_000
                topic, message, why = _convert(reader.deserialize(raw, conn.msgtype), conn, host_ns, camera_of,
                                               tree, base)
                if message is None:
                    skipped[conn.topic][f"{conn.msgtype}: {why}"] += 1
                    continue
                message.seq = seq[topic]
                seq[topic] += 1
                writer.write(topic, message)
                if conn.msgtype in (IMAGE, COMPRESSED):
                    frame_times.append(message.sensor_time_ns)
            counts = dict(writer.counts)
    finally:
        reader.close()
    drive_s = (max(frame_times) - min(frame_times)) / 1e9 if frame_times else 0.0
    listed = {topic: "; ".join(f"{why} ({n})" for why, n in reasons.items()) for topic, reasons in skipped.items()}
    return ImportSummary(out, counts, drive_s, time.perf_counter() - started), listed


def _first_frame(reader, conns: list, msgtype: str) -> str:
    first = next(reader.messages(connections=conns), None) if conns else None  # no connections: all of them
    return reader.deserialize(first[2], msgtype).header.frame_id.strip("/") if first else ""


def _gnss_velocity_connections(reader, navsat: list, skipped: dict[str, Counter]) -> list:
    """The TwistWithCovarianceStamped topics in the (first) NavSatFix's frame: the receiver's ENU velocity; every
    other twist topic listed as skipped."""
    twists = [c for c in reader.connections if c.msgtype == TWIST]
    antenna = _first_frame(reader, navsat, NAVSAT) if navsat and twists else ""
    chosen = []
    for conn in twists:
        frame = _first_frame(reader, [conn], TWIST)
        if navsat and frame == antenna:
            chosen.append(conn)
            continue
        why = (f"in frame {frame!r}, not the NavSatFix's {antenna!r} (a GNSS velocity is the antenna's, ENU)" if navsat
               else "no NavSatFix: a GNSS velocity goes with its fixes")
        skipped[conn.topic][f"{TWIST}: {why}"] += conn.msgcount
    return chosen


def _gnss_config(reader, navsat, imus, tree: ros.FrameTree, base: str) -> dict:
    gnss: dict = {"port": ""}
    for conns, key in ((navsat, "rate_hz"), (imus, "imu_rate_hz")):
        if conns:
            gnss[key] = round(_rate([t for _, t, _ in reader.messages(connections=conns)][:200]), 3)
    for conns, msgtype in ((navsat, NAVSAT), (imus, IMU_MSG)):
        first = next(reader.messages(connections=conns), None) if conns else None  # no connections: all of them
        frame = reader.deserialize(first[2], msgtype).header.frame_id if first else ""
        t = tree.lookup(base, frame) if frame else None
        if t is not None and msgtype == NAVSAT:
            gnss["antenna_lever_arm_m"] = [float(v) for v in t[:3, 3]]
        elif t is not None:
            gnss["imu_extrinsics"] = extrinsics(t)
    return gnss


def _convert(msg, conn, host_ns: int, camera_of: dict[str, str], tree: ros.FrameTree, base: str):
    """(topic, roadlog message or None, why not)."""
    if conn.msgtype == IMAGE:
        return camera_topic(camera_of[conn.topic]), *ros.image_frame(msg, camera_of[conn.topic], host_ns)
    if conn.msgtype == COMPRESSED:
        return camera_topic(camera_of[conn.topic]), *ros.compressed_frame(msg, camera_of[conn.topic], host_ns)
    if conn.msgtype == NAVSAT:
        return GNSS_FIX, *ros.gnss_fix(msg, host_ns)
    if conn.msgtype == IMU_MSG:
        return IMU, *ros.imu_sample(msg, host_ns)
    if conn.msgtype == TWIST:
        return GNSS_VELOCITY, *ros.gnss_velocity(msg, host_ns)
    if conn.msgtype == CLOUD:
        return LIDAR_POINTS, *ros.point_cloud(msg, host_ns)
    t_child_base = tree.lookup(msg.child_frame_id, base)  # Odometry: the child frame's pose -> the base's
    if t_child_base is None:
        return POSE, None, f"no transform from Odometry's child frame {msg.child_frame_id!r} to {base!r}"
    t_world_base = ros.matrix(msg.pose.pose.position, msg.pose.pose.orientation) @ t_child_base
    return POSE, vehicle_pose(t_world_base, ros.stamp_ns(msg.header), host_ns, msg.header.frame_id), ""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="the bag folder (metadata.yaml and its .db3/.mcap files)")
    parser.add_argument("--out", required=True, type=Path, help="the MCAP log to write")
    parser.add_argument("--base-frame", help="the vehicle frame (default: the Odometry's child frame, else base_link)")
    parser.add_argument("--reference-height-m", type=float, default=0.0,
                        help="the base frame above the road (m; 0: on the ground, as REP 105's base_footprint)")


@reports_config_errors
def run(args: argparse.Namespace) -> int:
    summary, skipped = import_bag(args.bag, args.out, base_frame=args.base_frame,
                                  reference_height_m=args.reference_height_m)
    for topic, why in skipped.items():
        print(f"skipped {topic}: {why}", file=sys.stderr)
    print(json.dumps(json.loads(summary.as_json()) | {"skipped": skipped}))
    return 0
