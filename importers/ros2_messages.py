"""ROS 2 messages (as rosbags deserialises them) -> roadlog messages: sensor_msgs Image / CompressedImage / CameraInfo /
NavSatFix / Imu / PointCloud2, geometry_msgs TwistWithCovarianceStamped (a GNSS velocity), nav_msgs Odometry, and tf2
transforms into one static frame tree. Each conversion returns None (and says why) for a message it cannot use, so the
importer counts it instead of failing."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.spine.messages import RAW_FORMAT_CHANNELS, CameraFrame, GnssFix, GnssVelocity, ImuSample, PointCloud
from daemon.spine.point_cloud_codec import pack_points

# trailing topic parts that name the stream, not the camera: /front/image_raw/compressed -> camera "front"
_STREAM_PARTS = {"image_raw", "image", "image_rect", "image_rect_color", "image_color", "image_mono", "compressed",
                 "camera_info", "color", "rgb"}


def stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def camera_name(topic: str) -> str:
    """The camera a topic belongs to, as a config name (lower case, [a-z0-9_], starting with a letter)."""
    parts = [p for p in topic.strip("/").split("/") if p]
    while len(parts) > 1 and parts[-1] in _STREAM_PARTS:
        parts.pop()
    name = re.sub(r"[^a-z0-9_]+", "_", "_".join(parts).lower()).strip("_") or "camera"
    return name if name[0].isalpha() else f"cam_{name}"


@dataclass(frozen=True)
class CameraInfo:
    width: int
    height: int
    k: np.ndarray  # 3x3
    distortion: tuple[float, float, float, float, float]
    frame_id: str


def camera_info(msg) -> tuple[CameraInfo | None, str]:
    d = [float(v) for v in msg.d]
    if msg.distortion_model not in ("plumb_bob", "rational_polynomial", "") or (d and len(d) < 5 and any(d)):
        return None, f"distortion model {msg.distortion_model!r} ({len(d)} coefficients) is not plumb_bob"
    if len(d) > 5 and any(d[5:]):
        return None, "rational_polynomial with k4-k6 set cannot be used as plumb_bob"
    k = np.asarray(msg.k, float).reshape(3, 3)
    if k[0, 0] <= 0 or k[1, 1] <= 0 or msg.width <= 0 or msg.height <= 0:
        return None, "no intrinsics (K or the image size is zero)"
    return CameraInfo(int(msg.width), int(msg.height), k, tuple((d + [0.0] * 5)[:5]), msg.header.frame_id), ""


def image_frame(msg, camera: str, host_ns: int) -> tuple[CameraFrame | None, str]:
    """sensor_msgs/Image in rgb8, bgr8 or mono8 (rows repacked when the step has padding)."""
    encoding = msg.encoding.lower()
    channels = RAW_FORMAT_CHANNELS.get(encoding)
    if channels is None:
        return None, f"Image encoding {msg.encoding!r} (rgb8, bgr8 and mono8 are imported)"
    row = msg.width * channels
    data = np.asarray(msg.data, np.uint8)
    if msg.step < row or len(data) < msg.step * msg.height:
        return None, f"Image of {len(data)} bytes for {msg.height} rows of step {msg.step}"
    pixels = data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, :row]
    return CameraFrame(sensor_time_ns=stamp_ns(msg.header), host_mono_ns=host_ns, camera=camera, format=encoding,
                       width=int(msg.width), height=int(msg.height), data=pixels.tobytes()), ""


def compressed_frame(msg, camera: str, host_ns: int) -> tuple[CameraFrame | None, str]:
    """sensor_msgs/CompressedImage in JPEG or PNG (image_transport writes e.g. "rgb8; jpeg compressed bgr8")."""
    fmt = next((f for f in ("jpeg", "png") if f in msg.format.lower()), None)
    if fmt is None:
        return None, f"CompressedImage format {msg.format!r} (jpeg and png are imported)"
    return CameraFrame(sensor_time_ns=stamp_ns(msg.header), host_mono_ns=host_ns, camera=camera, format=fmt,
                       data=bytes(np.asarray(msg.data, np.uint8))), ""


def gnss_fix(msg, host_ns: int) -> tuple[GnssFix | None, str]:
    if msg.status.status < 0:
        return None, "NavSatFix without a fix (status -1)"
    return GnssFix(sensor_time_ns=stamp_ns(msg.header), host_mono_ns=host_ns, latitude_deg=float(msg.latitude),
                   longitude_deg=float(msg.longitude), altitude_m=float(msg.altitude),
                   position_covariance=tuple(float(v) for v in msg.position_covariance),
                   covariance_type=int(msg.position_covariance_type)), ""


def imu_sample(msg, host_ns: int) -> tuple[ImuSample | None, str]:
    a, w = msg.linear_acceleration, msg.angular_velocity
    return ImuSample(sensor_time_ns=stamp_ns(msg.header), host_mono_ns=host_ns, accel_mps2=(a.x, a.y, a.z),
                     gyro_rps=(w.x, w.y, w.z)), ""


def gnss_velocity(msg, host_ns: int) -> tuple[GnssVelocity | None, str]:
    """A TwistWithCovarianceStamped of a GNSS receiver (the u-blox ROS driver's `fix_velocity`): twist.linear is the
    antenna's east/north/up velocity, the covariance's linear block its covariance (covariance_type 0 when it is all
    zero or marked unknown by a -1, else 2 when diagonal, 3 when not: ROS carries no finer type)."""
    v = msg.twist.twist.linear
    velocity = (float(v.x), float(v.y), float(v.z))
    if not all(np.isfinite(velocity)):
        return None, "TwistWithCovarianceStamped with a velocity that is not finite"
    block = np.asarray(msg.twist.covariance, float).reshape(6, 6)[:3, :3]
    if not np.all(np.isfinite(block)) or block[0, 0] < 0 or not np.any(block):
        return GnssVelocity(sensor_time_ns=stamp_ns(msg.header), host_mono_ns=host_ns, velocity_enu_mps=velocity), ""
    covariance_type = 2 if not np.any(block - np.diag(np.diag(block))) else 3
    return GnssVelocity(sensor_time_ns=stamp_ns(msg.header), host_mono_ns=host_ns, velocity_enu_mps=velocity,
                        velocity_covariance=tuple(float(c) for c in block.ravel()), covariance_type=covariance_type), ""


def matrix(translation, rotation) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat([rotation.x, rotation.y, rotation.z, rotation.w]).as_matrix()
    t[:3, 3] = (translation.x, translation.y, translation.z)
    return t


@dataclass
class FrameTree:
    """Static transforms (tf_static, and the first value of a /tf transform between two sensor frames): parent ->
    child 4x4 (a point in the child frame to the parent frame)."""

    edges: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)

    def add(self, transform) -> None:
        t = matrix(transform.transform.translation, transform.transform.rotation)
        self.edges.setdefault((transform.header.frame_id.strip("/"), transform.child_frame_id.strip("/")), t)

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """T_target_source (source-frame points into the target frame), through the tree either way."""
        target, source = target.strip("/"), source.strip("/")
        if target == source:
            return np.eye(4)
        graph: dict[str, list[tuple[str, np.ndarray]]] = {}
        for (parent, child), t in self.edges.items():
            graph.setdefault(parent, []).append((child, t))
            graph.setdefault(child, []).append((parent, np.linalg.inv(t)))
        best, todo = {target: np.eye(4)}, [target]
        while todo:  # breadth first from the target: best[f] = T_target_f
            frame = todo.pop(0)
            for neighbour, t in graph.get(frame, []):
                if neighbour not in best:
                    best[neighbour] = best[frame] @ t
                    todo.append(neighbour)
        return best.get(source)


_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}  # PointField.datatype
# per-point time fields of the common drivers: seconds after the stamp (Velodyne), ns after it (Ouster), absolute
# seconds (Hesai, RoboSense)
_TIME_FIELDS = (("time", 1.0, False), ("t", 1e-9, False), ("timestamp", 1.0, True))


def point_cloud(msg, host_ns: int) -> tuple[PointCloud | None, str]:
    """sensor_msgs/PointCloud2 with x, y, z (and intensity, a per-point time when it has one) as a PointCloud."""
    order = ">" if msg.is_bigendian else "<"
    fields = {f.name: (f.offset, _POINT_FIELD_TYPES.get(f.datatype)) for f in msg.fields if f.count == 1}
    if not all(fields.get(k, (0, None))[1] for k in ("x", "y", "z")):
        return None, "PointCloud2 without numeric x, y, z fields"
    count, step = int(msg.width) * int(msg.height), int(msg.point_step)
    data = np.asarray(msg.data, np.uint8)
    if step <= 0 or len(data) < count * step or any(o + np.dtype(t).itemsize > step for o, t in fields.values() if t):
        return None, f"PointCloud2 of {len(data)} bytes for {count} points of {step} bytes"
    rows = data[: count * step].reshape(count, step)

    def column(name: str) -> np.ndarray:
        offset, kind = fields[name]
        dtype = np.dtype(order + kind)
        return rows[:, offset:offset + dtype.itemsize].copy().view(dtype).ravel().astype(np.float64)

    xyz = np.column_stack([column(k) for k in ("x", "y", "z")])
    keep = np.all(np.isfinite(xyz), axis=1)  # unorganised gaps (NaN) are not points
    intensity = column("intensity") if fields.get("intensity", (0, None))[1] else None
    start_ns, time_s = stamp_ns(msg.header), None
    for name, scale, absolute in _TIME_FIELDS:
        if fields.get(name, (0, None))[1]:
            time_s = column(name)[keep] * scale
            if absolute and len(time_s):
                start_ns, time_s = int(round(time_s.min() * 1e9)), time_s - time_s.min()
            break
    return PointCloud(sensor_time_ns=start_ns, host_mono_ns=host_ns, sensor=msg.header.frame_id or "lidar",
                      data=pack_points(xyz[keep], None if intensity is None else intensity[keep], time_s)), ""
