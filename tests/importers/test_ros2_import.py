"""`roadlog import ros2`: a ROS 2 bag written with rosbags from a simulated drive (compressed and raw images,
camera infos, NavSatFix, the receiver's velocity as the u-blox ROS driver's TwistWithCovarianceStamped, Imu, Odometry,
tf_static, and topics the importer does not take) imported back, message
for message, with the car's cameras, antenna and IMU rebuilt from the bag's own calibration."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from scipy.spatial.transform import Rotation

from daemon.commands.cli import main as roadlog
from daemon.log_format.reader import read_log
from daemon.spine.messages import CameraFrame, GnssFix, GnssVelocity, ImuSample
from daemon.spine.point_cloud_codec import point_array
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU, LIDAR_POINTS, POSE, camera_topic
from exporters import ros2_messages as ros
from exporters.ros2_messages import BagWriter, T, header, transform
from mapping.offline.reconstruct_command import config_from_logs


@pytest.fixture(scope="module")
def sim_bag(city_drive, tmp_path_factory):
    """The simulated city drive as a ROS 2 bag, and what went into it."""
    config, _ = config_from_logs([str(city_drive)])
    wide, left, right = config.sensors.cameras
    records = list(read_log([city_drive], topics=[camera_topic(c.name) for c in (wide, left, right)]
                            + [GNSS_FIX, GNSS_VELOCITY, IMU]))
    path = tmp_path_factory.mktemp("bag") / "sim_bag"
    sent = {"wide": [], "left": [], "gnss": [], "velocity": [], "imu": [], "odom": [], "clouds": []}
    with Writer(path) as writer:
        bag = BagWriter(writer)
        statics = [transform("base_link", f"{c.name}_optical", c.extrinsics.matrix()) for c in (wide, left, right)]
        antenna = np.eye(4)
        antenna[:3, 3] = config.sensors.gnss.antenna_lever_arm_m
        imu_mount = np.eye(4)
        imu_mount[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
        statics += [transform("base_link", "gnss_antenna", antenna), transform("base_link", "imu_link", imu_mount)]
        bag.write("/tf_static", "tf2_msgs/msg/TFMessage", 1, T["tf2_msgs/msg/TFMessage"](transforms=statics))
        for cam in (wide, left):
            bag.write(f"/{cam.name}/camera_info", ros.INFO, 2, ros.camera_info(cam, 0, f"{cam.name}_optical"))
        for r in records:
            m, host = r.message, r.message.host_mono_ns
            if isinstance(m, CameraFrame) and m.camera == wide.name:
                bag.write("/front_wide/image_raw/compressed", ros.COMPRESSED, host,
                          ros.compressed_image(m, m.sensor_time_ns, "front_wide_optical"))
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
                bag.write("/front_right/image_raw/compressed", ros.COMPRESSED, host,
                          ros.compressed_image(m, m.sensor_time_ns, "front_right_optical"))
            elif isinstance(m, GnssFix):
                bag.write("/gnss/fix", ros.NAVSAT, host, ros.nav_sat_fix(m, m.sensor_time_ns, "gnss_antenna"))
                sent["gnss"].append(m)
                odom_pose = np.eye(4)
                odom_pose[:3, :3] = Rotation.from_euler("z", 0.01 * len(sent["odom"])).as_matrix()
                odom_pose[:3, 3] = (2.0 * len(sent["odom"]), 0.1, 0.0)
                bag.write("/odom", ros.ODOMETRY, host, ros.odometry(
                    odom_pose[:3, 3], Rotation.from_matrix(odom_pose[:3, :3]).as_quat(), m.sensor_time_ns, "odom",
                    "base_link"))
                sent["odom"].append(odom_pose)
            elif isinstance(m, GnssVelocity):  # ENU in the antenna's frame, as the u-blox ROS driver has it
                bag.write("/ublox/fix_velocity", ros.TWIST, host, ros.gnss_velocity(m, m.sensor_time_ns,
                                                                                    "gnss_antenna"))
                bag.write("/vehicle/twist", ros.TWIST, host, ros.gnss_velocity(m, m.sensor_time_ns, "base_link"))
                sent["velocity"].append(m)
            elif isinstance(m, ImuSample):
                bag.write("/imu/data", ros.IMU_MSG, host, ros.imu(m, m.sensor_time_ns, "imu_link"))
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
    assert printed["skipped"]["/vehicle/twist"] == (  # a twist in another frame is no GNSS velocity
        f"{ros.TWIST}: in frame 'base_link', not the NavSatFix's 'gnss_antenna' (a GNSS velocity is the antenna's, "
        f"ENU) ({len(sent['velocity'])})")
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
    assert len(sent["velocity"]) == len(sent["gnss"]) > 10
    assert [(v.velocity_enu_mps, v.velocity_covariance, v.covariance_type, v.sensor_time_ns, v.host_mono_ns)
            for v in by_topic[GNSS_VELOCITY]] == [(m.velocity_enu_mps, m.velocity_covariance, m.covariance_type,
                                                   m.sensor_time_ns, m.host_mono_ns) for m in sent["velocity"]]
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


def test_a_bag_of_images_alone_imports(tmp_path):
    """No Odometry, NavSatFix or Imu topic: nothing is read as one of them (rosbags reads every connection when
    given none)."""
    from daemon.spine.config import CameraConfig

    cam = CameraConfig(name="front", backend="recorded", width=32, height=24, rate_hz=10.0,
                       intrinsics={"fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0}, extrinsics={})
    jpeg = cv2.imencode(".jpg", np.full((24, 32, 3), 128, np.uint8))[1].tobytes()
    with Writer(tmp_path / "bag") as writer:
        bag = BagWriter(writer)
        bag.write("/tf_static", ros.TF, 1, ros.tf_message([transform("base_link", "front", np.eye(4))]))
        for k in range(3):
            stamp = 10**18 + k * 10**8
            bag.write("/front/camera_info", ros.INFO, stamp, ros.camera_info(cam, stamp, "front"))
            bag.write("/front/image_raw/compressed", ros.COMPRESSED, stamp,
                      ros.compressed_image(CameraFrame(format="jpeg", data=jpeg), stamp, "front"))
    assert roadlog(["import", "ros2", str(tmp_path / "bag"), "--out", str(tmp_path / "x.mcap")]) == 0
    frames = [r.message for r in read_log([tmp_path / "x.mcap"]) if r.topic == camera_topic("front")]
    assert [f.data for f in frames] == [jpeg] * 3
