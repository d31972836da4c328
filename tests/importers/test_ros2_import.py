"""`roadlog import ros2`: a ROS 2 bag written with rosbags from a simulated drive (compressed and raw images,
camera infos, NavSatFix, Imu, Odometry, tf_static, and topics the importer does not take) imported back, message
for message, with the car's cameras, antenna and IMU rebuilt from the bag's own calibration."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from daemon.commands.cli import main as roadlog
from daemon.log_format.reader import read_log
from daemon.spine.messages import CameraFrame, GnssFix, ImuSample
from daemon.spine.point_cloud_codec import point_array
from daemon.spine.topics import GNSS_FIX, IMU, LIDAR_POINTS, POSE, camera_topic
from mapping.offline.reconstruct_command import config_from_logs

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types


def header(ns: int, frame: str):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame)


def transform(parent: str, child: str, m: np.ndarray):
    q = Rotation.from_matrix(m[:3, :3]).as_quat()
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(0, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](*m[:3, 3]),
                                                   rotation=T["geometry_msgs/msg/Quaternion"](*q)))


def vector(v) -> object:
    return T["geometry_msgs/msg/Vector3"](*(float(x) for x in v))


class Bag:
    def __init__(self, writer: Writer):
        self.writer, self.connections = writer, {}

    def write(self, topic: str, msgtype: str, host_ns: int, msg) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=TS)
        self.writer.write(self.connections[topic], host_ns, TS.serialize_cdr(msg, msgtype))


@pytest.fixture(scope="module")
def sim_bag(city_drive, tmp_path_factory):
    """The simulated city drive as a ROS 2 bag, and what went into it."""
    config, _ = config_from_logs([str(city_drive)])
    wide, left, right = config.sensors.cameras
    records = list(read_log([city_drive], topics=[camera_topic(c.name) for c in (wide, left, right)] + [GNSS_FIX, IMU]))
    path = tmp_path_factory.mktemp("bag") / "sim_bag"
    sent = {"wide": [], "left": [], "gnss": [], "imu": [], "odom": [], "clouds": []}
    with Writer(path) as writer:
        bag = Bag(writer)
        statics = [transform("base_link", f"{c.name}_optical", c.extrinsics.matrix()) for c in (wide, left, right)]
        antenna = np.eye(4)
        antenna[:3, 3] = config.sensors.gnss.antenna_lever_arm_m
        imu_mount = np.eye(4)
        imu_mount[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
        statics += [transform("base_link", "gnss_antenna", antenna), transform("base_link", "imu_link", imu_mount)]
        bag.write("/tf_static", "tf2_msgs/msg/TFMessage", 1, T["tf2_msgs/msg/TFMessage"](transforms=statics))
        for cam in (wide, left):
            k = cam.intrinsics.matrix()
            bag.write(f"/{cam.name}/camera_info", "sensor_msgs/msg/CameraInfo", 2, T["sensor_msgs/msg/CameraInfo"](
                header=header(0, f"{cam.name}_optical"), height=cam.height, width=cam.width,
                distortion_model="plumb_bob", d=np.array(cam.distortion, float), k=k.ravel(), r=np.eye(3).ravel(),
                p=np.column_stack([k, np.zeros(3)]).ravel(), binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                          do_rectify=False)))
        for r in records:
            m, host = r.message, r.message.host_mono_ns
            if isinstance(m, CameraFrame) and m.camera == wide.name:
                bag.write("/front_wide/image_raw/compressed", "sensor_msgs/msg/CompressedImage", host,
                          T["sensor_msgs/msg/CompressedImage"](header=header(m.sensor_time_ns, "front_wide_optical"),
                                                               format="jpeg", data=np.frombuffer(m.data, np.uint8)))
                sent["wide"].append(m)
            elif isinstance(m, CameraFrame) and m.camera == left.name:
                rgb = cv2.cvtColor(cv2.imdecode(np.frombuffer(m.data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
                padded = np.zeros((rgb.shape[0], rgb.shape[1] * 3 + 8), np.uint8)  # a step with row padding
                padded[:, :rgb.shape[1] * 3] = rgb.reshape(rgb.shape[0], -1)
                bag.write("/front_left/image_raw", "sensor_msgs/msg/Image", host, T["sensor_msgs/msg/Image"](
                    header=header(m.sensor_time_ns, "front_left_optical"), height=rgb.shape[0], width=rgb.shape[1],
                    encoding="rgb8", is_bigendian=0, step=padded.shape[1], data=padded.ravel()))
                sent["left"].append((m, rgb))
            elif isinstance(m, CameraFrame):  # no camera info for this one: listed as skipped
                bag.write("/front_right/image_raw/compressed", "sensor_msgs/msg/CompressedImage", host,
                          T["sensor_msgs/msg/CompressedImage"](header=header(m.sensor_time_ns, "front_right_optical"),
                                                               format="jpeg", data=np.frombuffer(m.data, np.uint8)))
            elif isinstance(m, GnssFix):
                bag.write("/gnss/fix", "sensor_msgs/msg/NavSatFix", host, T["sensor_msgs/msg/NavSatFix"](
                    header=header(m.sensor_time_ns, "gnss_antenna"),
                    status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1), latitude=m.latitude_deg,
                    longitude=m.longitude_deg, altitude=m.altitude_m,
                    position_covariance=np.array(m.position_covariance, float), position_covariance_type=2))
                sent["gnss"].append(m)
                odom_pose = np.eye(4)
                odom_pose[:3, :3] = Rotation.from_euler("z", 0.01 * len(sent["odom"])).as_matrix()
                odom_pose[:3, 3] = (2.0 * len(sent["odom"]), 0.1, 0.0)
                q = Rotation.from_matrix(odom_pose[:3, :3]).as_quat()
                pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](*odom_pose[:3, 3]),
                                                   orientation=T["geometry_msgs/msg/Quaternion"](*q))
                bag.write("/odom", "nav_msgs/msg/Odometry", host, T["nav_msgs/msg/Odometry"](
                    header=header(m.sensor_time_ns, "odom"), child_frame_id="base_link",
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](
                        twist=T["geometry_msgs/msg/Twist"](linear=vector((0, 0, 0)), angular=vector((0, 0, 0))),
                        covariance=np.zeros(36))))
                sent["odom"].append(odom_pose)
            elif isinstance(m, ImuSample):
                bag.write("/imu/data", "sensor_msgs/msg/Imu", host, T["sensor_msgs/msg/Imu"](
                    header=header(m.sensor_time_ns, "imu_link"),
                    orientation=T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
                    orientation_covariance=np.zeros(9), angular_velocity=vector(m.gyro_rps),
                    angular_velocity_covariance=np.zeros(9), linear_acceleration=vector(m.accel_mps2),
                    linear_acceleration_covariance=np.zeros(9)))
                sent["imu"].append(m)
        for i in range(3):
            bag.write("/chatter", "std_msgs/msg/String", 10 + i, T["std_msgs/msg/String"](data=f"hello {i}"))
        rng = np.random.default_rng(4)
        lidar_mount = config.sensors.lidar.extrinsics.matrix()
        bag.write("/tf_static", "tf2_msgs/msg/TFMessage", 3, T["tf2_msgs/msg/TFMessage"](
            transforms=[transform("base_link", "os_lidar", lidar_mount)]))
        point = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "<u4"), ("intensity", "<f4"),
                          ("t", "<u4")])  # an Ouster ROS driver's layout: t in ns after the stamp
        fields = [T["sensor_msgs/msg/PointField"](name=n, offset=point.fields[n][1], datatype=d, count=1)
                  for n, d in (("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("t", 6))]
        start = records[0].message.host_mono_ns
        for k in range(3):
            cloud = np.zeros(500, point)
            for axis in ("x", "y", "z", "intensity"):
                cloud[axis] = rng.normal(0, 5, 500)
            cloud["t"] = rng.integers(0, 100_000_000, 500)
            bag.write("/ouster/points", "sensor_msgs/msg/PointCloud2", start + k * 100_000_000,
                      T["sensor_msgs/msg/PointCloud2"](header=header(start + k * 100_000_000, "os_lidar"), height=1,
                                                       width=500, fields=fields, is_bigendian=False,
                                                       point_step=point.itemsize, row_step=point.itemsize * 500,
                                                       data=np.frombuffer(cloud.tobytes(), np.uint8),
                                                       is_dense=True))
            sent["clouds"].append((start + k * 100_000_000, cloud))
    return path, config, sent


def test_a_ros2_bag_imports_message_for_message(sim_bag, tmp_path, capsys):
    path, config, sent = sim_bag
    out = tmp_path / "imported.mcap"
    assert roadlog(["import", "ros2", str(path), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    printed = json.loads(captured.out.strip().splitlines()[-1])
    assert "/chatter" in printed["skipped"] and "std_msgs/msg/String: not an imported type (3)" in \
        printed["skipped"]["/chatter"]
    assert "no usable CameraInfo for camera 'front_right'" in printed["skipped"]["/front_right/image_raw/compressed"]
    assert "skipped /chatter" in captured.err
    records = list(read_log([out]))
    by_topic = {}
    for r in records:
        by_topic.setdefault(r.topic, []).append(r.message)
    wide = by_topic[camera_topic("front_wide")]
    assert [(f.data, f.format, f.sensor_time_ns, f.host_mono_ns) for f in wide] == [
        (m.data, "jpeg", m.sensor_time_ns, m.host_mono_ns) for m in sent["wide"]]
    left = by_topic[camera_topic("front_left")]
    assert len(left) == len(sent["left"]) and all(f.format == "rgb8" for f in left)
    for frame, (m, rgb) in zip(left, sent["left"], strict=True):
        assert frame.sensor_time_ns == m.sensor_time_ns and frame.data == rgb.tobytes()
    assert [(f.latitude_deg, f.longitude_deg, f.altitude_m, f.position_covariance, f.sensor_time_ns)
            for f in by_topic[GNSS_FIX]] == [(m.latitude_deg, m.longitude_deg, m.altitude_m, m.position_covariance,
                                              m.sensor_time_ns) for m in sent["gnss"]]
    assert [(s.accel_mps2, s.gyro_rps, s.sensor_time_ns, s.host_mono_ns) for s in by_topic[IMU]] == [
        (m.accel_mps2, m.gyro_rps, m.sensor_time_ns, m.host_mono_ns) for m in sent["imu"]]
    poses = by_topic[POSE]
    np.testing.assert_allclose([p.position_m for p in poses], [m[:3, 3] for m in sent["odom"]], atol=1e-12)
    assert camera_topic("front_right") not in by_topic
    imported, _ = config_from_logs([str(out)])
    assert sorted(c.name for c in imported.sensors.cameras) == ["front_left", "front_wide"]
    for cam in imported.sensors.cameras:
        original = next(c for c in config.sensors.cameras if c.name == cam.name)
        np.testing.assert_allclose(cam.intrinsics.matrix(), original.intrinsics.matrix())
        np.testing.assert_allclose(cam.extrinsics.matrix(), original.extrinsics.matrix(), atol=1e-9)
        assert (cam.width, cam.height, cam.distortion, cam.backend) == (original.width, original.height,
                                                                         original.distortion, "recorded")
    clouds = by_topic[LIDAR_POINTS]
    assert len(clouds) == 3 and imported.sensors.lidar.model == "point-cloud"
    np.testing.assert_allclose(imported.sensors.lidar.extrinsics.matrix(), config.sensors.lidar.extrinsics.matrix(),
                               atol=1e-9)
    for cloud, (stamp, points) in zip(clouds, sent["clouds"], strict=True):
        got = point_array(cloud)
        assert cloud.sensor_time_ns == stamp
        np.testing.assert_array_equal(got[:, :4], np.column_stack([points[k] for k in ("x", "y", "z", "intensity")]))
        np.testing.assert_allclose(got[:, 4], points["t"] * 1e-9, rtol=1e-6)
    gnss = imported.sensors.gnss
    assert gnss.antenna_lever_arm_m == pytest.approx(config.sensors.gnss.antenna_lever_arm_m)
    assert gnss.imu_extrinsics.rotation_rpy_deg == pytest.approx((0.0, 0.0, 90.0))
    assert gnss.imu_rate_hz == pytest.approx(100.0, rel=0.05) and gnss.rate_hz == pytest.approx(10.0, rel=0.05)


def test_what_is_not_a_ros2_bag_is_a_clear_error(tmp_path, capsys):
    folder = tmp_path / "not_a_bag"
    folder.mkdir()
    (folder / "metadata.yaml").write_text("just: text\n")
    assert roadlog(["import", "ros2", str(folder), "--out", str(tmp_path / "x.mcap")]) == 2
    assert roadlog(["import", "ros2", str(tmp_path / "absent"), "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert "not a readable ROS 2 bag" in err and "no such bag" in err and "Traceback" not in err
    assert not (tmp_path / "x.mcap").exists()


def test_reconstruct_and_log_info_given_a_bag_say_to_import_it(sim_bag, tmp_path, capsys):
    path, _, _ = sim_bag
    storage = next(path.glob("*.db3"))
    assert roadlog(["reconstruct", str(path), "--out", str(tmp_path / "map")]) == 2
    assert roadlog(["reconstruct", str(storage), "--out", str(tmp_path / "map")]) == 2
    assert roadlog(["log-info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("is a ROS 2 bag: import it first (roadlog import ros2") == 2
    assert "sqlite3 storage" in err and "Traceback" not in err


def test_a_point_cloud2_without_xyz_or_with_torn_data_is_refused_with_a_reason():
    from importers.ros2_messages import point_cloud

    def cloud(names, size):
        fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in
                  enumerate(names)]
        return T["sensor_msgs/msg/PointCloud2"](header=header(5, "lidar"), height=1, width=10, fields=fields,
                                                is_bigendian=False, point_step=12, row_step=120,
                                                data=np.zeros(size, np.uint8), is_dense=True)

    assert point_cloud(cloud(("x", "y"), 120), 0) == (None, "PointCloud2 without numeric x, y, z fields")
    message, why = point_cloud(cloud(("x", "y", "z"), 100), 0)
    assert message is None and "100 bytes for 10 points" in why
    message, why = point_cloud(cloud(("x", "y", "z"), 120), 7)
    assert why == "" and message.sensor_time_ns == 5 and len(point_array(message)) == 10
