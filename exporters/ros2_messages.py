"""roadlog messages -> ROS 2 messages (rosbags' Humble types, ready for `serialize_cdr`): std_msgs Header,
tf2 transforms, sensor_msgs Image / CompressedImage / CameraInfo / NavSatFix / Imu / PointCloud2, geometry_msgs
TwistWithCovarianceStamped (the GNSS velocity), nav_msgs Odometry;
and `BagWriter`, a rosbags writer that adds each topic's connection on its first message. The inverse of
`importers/ros2_messages.py`: what one writes the other reads back."""

from __future__ import annotations

import numpy as np
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from daemon.spine.config import CameraConfig
from daemon.spine.messages import RAW_FORMAT_CHANNELS, CameraFrame, GnssFix, GnssVelocity, ImuSample

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
T = TYPESTORE.types
IMAGE, COMPRESSED, INFO = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
NAVSAT, IMU_MSG, CLOUD = "sensor_msgs/msg/NavSatFix", "sensor_msgs/msg/Imu", "sensor_msgs/msg/PointCloud2"
ODOMETRY, TF = "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage"
TWIST = "geometry_msgs/msg/TwistWithCovarianceStamped"
TWIST_ANGULAR_UNKNOWN = 21  # covariance[3 * 6 + 3] = -1: no angular velocity (the u-blox ROS driver's, REP 145's -1)
# PointCloud2 layout: float32 x, y, z, intensity and uint32 t, the firing time in ns after header.stamp (the Ouster
# ROS driver's `t`, which the importer reads back)
CLOUD_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<u4")])
_FLOAT32, _UINT32 = 7, 6  # sensor_msgs/PointField datatypes


class BagWriter:
    """A rosbags Writer whose topics get their connection on their first message."""

    def __init__(self, writer: Writer):
        self.writer, self.connections = writer, {}

    def connect(self, topic: str, msgtype: str) -> None:
        """Add the topic's connection now (a reader takes the first of two topics of one type first)."""
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=TYPESTORE)

    def write(self, topic: str, msgtype: str, receive_ns: int, msg) -> None:
        self.connect(topic, msgtype)
        self.writer.write(self.connections[topic], receive_ns, TYPESTORE.serialize_cdr(msg, msgtype))


def header(stamp_ns: int, frame: str):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                                           nanosec=stamp_ns % 10**9), frame_id=frame)


def vector(v):
    return T["geometry_msgs/msg/Vector3"](*(float(x) for x in v))


def quaternion(xyzw):
    return T["geometry_msgs/msg/Quaternion"](*(float(x) for x in xyzw))


def transform(parent: str, child: str, m: np.ndarray, stamp_ns: int = 0):
    """A TransformStamped: `m` (4x4) takes points in `child` into `parent` (the child's pose in the parent)."""
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(stamp_ns, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](translation=vector(m[:3, 3]),
                                                   rotation=quaternion(Rotation.from_matrix(m[:3, :3]).as_quat())))


def tf_message(transforms: list):
    return T["tf2_msgs/msg/TFMessage"](transforms=transforms)


def camera_info(cam: CameraConfig, stamp_ns: int, frame: str):
    """plumb_bob with the config's k1 k2 p1 p2 k3; R identity, P = [K | 0] (an unrectified camera)."""
    k = cam.intrinsics.matrix()
    return T[INFO](header=header(stamp_ns, frame), height=cam.height, width=cam.width, distortion_model="plumb_bob",
                   d=np.array(cam.distortion, float), k=k.ravel(), r=np.eye(3).ravel(),
                   p=np.column_stack([k, np.zeros(3)]).ravel(), binning_x=0, binning_y=0,
                   roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                             do_rectify=False))


def compressed_image(frame: CameraFrame, stamp_ns: int, frame_id: str):
    return T[COMPRESSED](header=header(stamp_ns, frame_id), format=frame.format,
                         data=np.frombuffer(frame.data, np.uint8))


def raw_image(frame: CameraFrame, stamp_ns: int, frame_id: str):
    """A raw frame (rgb8, bgr8, mono8) as it is: rows without padding."""
    step = frame.width * RAW_FORMAT_CHANNELS[frame.format]
    return T[IMAGE](header=header(stamp_ns, frame_id), height=frame.height, width=frame.width, encoding=frame.format,
                    is_bigendian=0, step=step, data=np.frombuffer(frame.data, np.uint8))


def nav_sat_fix(fix: GnssFix, stamp_ns: int, frame_id: str):
    """status FIX (a roadlog fix is one), service GPS; the covariance type means the same in both (0-3)."""
    return T[NAVSAT](header=header(stamp_ns, frame_id), status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                     latitude=fix.latitude_deg, longitude=fix.longitude_deg, altitude=fix.altitude_m,
                     position_covariance=np.array(fix.position_covariance, float),
                     position_covariance_type=int(fix.covariance_type))


def imu(sample: ImuSample, stamp_ns: int, frame_id: str):
    """No orientation (orientation_covariance[0] = -1, REP 145); covariances unknown (zero)."""
    no_orientation = np.zeros(9)
    no_orientation[0] = -1.0
    return T[IMU_MSG](header=header(stamp_ns, frame_id), orientation=quaternion((0.0, 0.0, 0.0, 1.0)),
                      orientation_covariance=no_orientation, angular_velocity=vector(sample.gyro_rps),
                      angular_velocity_covariance=np.zeros(9), linear_acceleration=vector(sample.accel_mps2),
                      linear_acceleration_covariance=np.zeros(9))


def gnss_velocity(velocity: GnssVelocity, stamp_ns: int, frame_id: str):
    """The antenna's ENU velocity as the u-blox ROS driver publishes it (`fix_velocity`): twist.linear east, north, up
    in m/s, the 3x3 covariance in the linear block (all zero when unknown, as NavSatFix's type 0), angular velocity
    zero and marked unknown by covariance[21] = -1."""
    covariance = np.zeros((6, 6))
    if velocity.covariance_type != 0:
        covariance[:3, :3] = np.reshape(velocity.velocity_covariance, (3, 3))
    covariance = covariance.ravel()
    covariance[TWIST_ANGULAR_UNKNOWN] = -1.0
    twist = T["geometry_msgs/msg/Twist"](linear=vector(velocity.velocity_enu_mps), angular=vector((0.0, 0.0, 0.0)))
    return T[TWIST](header=header(stamp_ns, frame_id),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=covariance))


def point_cloud(xyz: np.ndarray, intensity: np.ndarray | None, t_ns: np.ndarray, stamp_ns: int, frame_id: str):
    """One scan as an unorganised PointCloud2 (height 1) of CLOUD_POINT records, in the scan's order."""
    cloud = np.zeros(len(xyz), CLOUD_POINT)
    cloud["x"], cloud["y"], cloud["z"] = (np.asarray(xyz, np.float32)[:, k] for k in range(3))
    if intensity is not None:
        cloud["intensity"] = intensity
    cloud["t"] = t_ns
    fields = [T["sensor_msgs/msg/PointField"](name=name, offset=CLOUD_POINT.fields[name][1],
                                              datatype=_UINT32 if name == "t" else _FLOAT32, count=1)
              for name in CLOUD_POINT.names]
    return T[CLOUD](header=header(stamp_ns, frame_id), height=1, width=len(cloud), fields=fields, is_bigendian=False,
                    point_step=CLOUD_POINT.itemsize, row_step=CLOUD_POINT.itemsize * len(cloud),
                    data=np.frombuffer(cloud.tobytes(), np.uint8), is_dense=True)


def odometry(position, orientation_xyzw, stamp_ns: int, frame_id: str, child_frame_id: str):
    """The vehicle's pose in `frame_id`; no twist, covariances unknown (zero)."""
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](*(float(v) for v in position)),
                                       orientation=quaternion(orientation_xyzw))
    return T[ODOMETRY](header=header(stamp_ns, frame_id), child_frame_id=child_frame_id,
                       pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                       twist=T["geometry_msgs/msg/TwistWithCovariance"](
                           twist=T["geometry_msgs/msg/Twist"](linear=vector((0, 0, 0)), angular=vector((0, 0, 0))),
                           covariance=np.zeros(36)))
