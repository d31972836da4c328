"""`roadlog export ros2`: the simulated city drive (and a log of vehicle poses beside it) exported to a ROS 2 bag and
imported back with `roadlog import ros2`, both as real processes, compared message for message with the original: frames
byte for byte, fixes, the receiver's velocities and IMU samples value for value, the cameras' calibration and every
sensor's extrinsics as recorded, the Lidar's points as decoding its packets gives them, the stamps on UTC."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation

from daemon.commands.cli import main as roadlog
from daemon.log_format.reader import read_log
from daemon.log_format.static_transforms import sensor_frames
from daemon.log_format.writer import LogWriter
from daemon.spine.messages import GnssVelocity, VehiclePose
from daemon.spine.point_cloud_codec import point_array
from daemon.spine.topics import (
    GNSS_FIX,
    GNSS_VELOCITY,
    IMU,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    MAP_FRAME,
    POSE,
    TIME_ANCHOR,
    VEHICLE_POSE,
    camera_topic,
)
from exporters import ros2_messages as ros
from exporters.ros2_bag import ODOM_TOPIC
from exporters.ros2_messages import TYPESTORE
from importers import ros2_messages as ros_in
from importers.ros2_messages import matrix
from mapping.inputs.drive_inputs import fix_velocities
from mapping.inputs.lidar_ground import configured_decoding, packet_scans
from mapping.offline.reconstruct_command import config_from_logs
from tests.conftest import REPO

ROADLOG = REPO / ".venv" / "bin" / "roadlog"  # the installed console script


def by_topic(path) -> dict[str, list]:
    out: dict[str, list] = {}
    for r in read_log([path]):
        out.setdefault(r.topic, []).append(r.message)
    return out


@pytest.fixture(scope="module")
def round_trip(city_drive, tmp_path_factory):
    """(original messages, its config, the poses log's poses, the bag, the imported log's messages, its config)."""
    folder = tmp_path_factory.mktemp("ros2_export")
    config, config_path = config_from_logs([str(city_drive)])
    original = by_topic(city_drive)
    frames = original[camera_topic(config.sensors.cameras[0].name)]
    poses = [VehiclePose(seq=k, sensor_time_ns=f.host_mono_ns, host_mono_ns=f.host_mono_ns, frame_id="enu",
                         position_m=(1.5 * k, 0.25 * k, 0.01 * k),
                         orientation_xyzw=tuple(Rotation.from_euler("z", 0.02 * k).as_quat()))
             for k, f in enumerate(frames[:20])]
    pose_log = folder / "poses.mcap"  # another system's localisation, logged beside the drive
    writer = LogWriter(pose_log, config, log_time_offset_ns=0)
    for pose in poses:
        writer.write(POSE, pose)
    writer.close()
    bag, back = folder / "drive_bag", folder / "back.mcap"
    exported = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "export", "ros2", str(city_drive),
                               str(pose_log), "--out", str(bag)], cwd=REPO, capture_output=True, text=True,
                              timeout=120)
    assert exported.returncode == 0, exported.stderr
    imported = subprocess.run([str(ROADLOG), "import", "ros2", str(bag), "--out", str(back), "--reference-height-m",
                               str(config.vehicle.reference_height_m)], cwd=REPO, capture_output=True, text=True,
                              timeout=120)
    assert imported.returncode == 0, imported.stderr
    back_config, _ = config_from_logs([str(back)])
    return dict(original=original, config=config, config_path=config_path, poses=poses, bag=bag,
                export=exported, back=by_topic(back), back_config=back_config, summary=json.loads(
                    imported.stdout.strip().splitlines()[-1]))


def utc_minus_mono(original) -> int:
    diffs = {a.utc_ns - a.host_mono_ns for a in original[TIME_ANCHOR]}
    assert len(diffs) == 1  # the simulator's UTC runs with its monotonic clock
    return diffs.pop()


def test_what_is_not_exported_is_listed_with_its_count(round_trip):
    err = round_trip["export"].stderr
    for topic, n in (("can/frames", 500), ("wheel_speeds", 250), ("mask/front_wide", 50)):
        assert f"not exported {topic}: not exported ({n})" in err
    assert f"not exported {GNSS_VELOCITY}" not in err
    printed = json.loads(round_trip["export"].stdout.strip().splitlines()[-1])
    assert printed["messages"]["/lidar/points"] == len(round_trip["back"][LIDAR_POINTS])
    # the importer takes everything the bag holds but the Lidar's IMU (it imports one Imu topic: the car's)
    assert round_trip["summary"]["skipped"] == {
        "/lidar/imu": "sensor_msgs/msg/Imu: a second Imu topic (the first is imported) (500)"}
    assert set(round_trip["summary"]["messages"]) >= {GNSS_FIX, GNSS_VELOCITY, IMU, LIDAR_POINTS, POSE}


def test_frames_come_back_byte_for_byte_stamped_in_utc(round_trip):
    original, back, offset = round_trip["original"], round_trip["back"], utc_minus_mono(round_trip["original"])
    for cam in round_trip["config"].sensors.cameras:
        sent, got = original[camera_topic(cam.name)], back[camera_topic(cam.name)]
        assert [(f.data, f.format) for f in got] == [(f.data, f.format) for f in sent]
        # camera stamps are on the host clock: moved onto UTC, as the receive times
        assert [f.sensor_time_ns for f in got] == [f.sensor_time_ns + offset for f in sent]
        assert [f.host_mono_ns for f in got] == [f.host_mono_ns + offset for f in sent]


def test_fixes_and_imu_samples_come_back_value_for_value(round_trip):
    original, back, offset = round_trip["original"], round_trip["back"], utc_minus_mono(round_trip["original"])
    assert [(f.latitude_deg, f.longitude_deg, f.altitude_m, f.position_covariance, f.covariance_type,
             f.sensor_time_ns) for f in back[GNSS_FIX]] == [
        (f.latitude_deg, f.longitude_deg, f.altitude_m, f.position_covariance, f.covariance_type, f.sensor_time_ns)
        for f in original[GNSS_FIX]]  # GNSS stamps are UTC already: as they are
    sent, got = original[IMU], back[IMU]  # the car's IMU (the Lidar's is the bag's second Imu topic)
    assert [(s.accel_mps2, s.gyro_rps) for s in got] == [(s.accel_mps2, s.gyro_rps) for s in sent]
    # a free-running IMU clock: put on the host clock by the mapper's fit (shortest latency), then on UTC
    lag = np.array([g.sensor_time_ns - (s.host_mono_ns + offset) for g, s in zip(got, sent, strict=True)])
    assert np.all(lag <= 0) and np.all(lag > -20_000_000)


def test_gnss_velocities_are_enu_twists_stamped_as_their_fixes_and_come_back_value_for_value(round_trip):
    """TwistWithCovarianceStamped as the u-blox ROS driver writes it: linear = the antenna's east/north/up velocity
    in frame `gnss`, the covariance in the 6x6's linear block, the angular velocity unknown (covariance[21] = -1)."""
    sent, got = round_trip["original"][GNSS_VELOCITY], round_trip["back"][GNSS_VELOCITY]
    assert len(sent) == len(round_trip["original"][GNSS_FIX]) > 40
    assert [(v.velocity_enu_mps, v.velocity_covariance, v.covariance_type, v.sensor_time_ns) for v in got] == [
        (v.velocity_enu_mps, v.velocity_covariance, v.covariance_type, v.sensor_time_ns) for v in sent]
    fixes = {ros_in.stamp_ns(m.header) for _, m in _bag_messages(round_trip["bag"], "/gnss/fix")}
    twists = _bag_messages(round_trip["bag"], "/gnss/velocity")
    assert len(twists) == len(sent)
    for (_, msg), v in zip(twists, sent, strict=True):
        assert msg.header.frame_id == "gnss" and ros_in.stamp_ns(msg.header) in fixes
        linear, angular = msg.twist.twist.linear, msg.twist.twist.angular
        assert (linear.x, linear.y, linear.z) == v.velocity_enu_mps and (angular.x, angular.y, angular.z) == (0, 0, 0)
        covariance = np.reshape(msg.twist.covariance, (6, 6))
        np.testing.assert_array_equal(covariance[:3, :3], np.reshape(v.velocity_covariance, (3, 3)))
        assert covariance[3, 3] == -1.0 and np.count_nonzero(covariance[3:, :]) == 1 and not covariance[:3, 3:].any()
    velocity, _ = fix_velocities(round_trip["back"][GNSS_FIX], got)  # the fusion finds each fix's velocity
    assert np.all(np.isfinite(velocity))


def test_an_nmea_velocity_and_an_unknown_one_keep_their_meaning_through_a_twist():
    """An NMEA receiver's velocity (horizontal only: the vertical's variance huge) and one of unknown covariance,
    through CDR bytes and back: the values as they were; the type 2 (diagonal), ROS having no "approximated", and 0."""
    nmea = GnssVelocity(sensor_time_ns=1_700_000_000_100_000_000, velocity_enu_mps=(3.5, -1.25, 0.0),
                        velocity_covariance=(0.0625, 0, 0, 0, 0.0625, 0, 0, 0, 1e6), covariance_type=1)
    unknown = GnssVelocity(sensor_time_ns=1_700_000_000_200_000_000, velocity_enu_mps=(0.5, 0.25, -0.125))
    back = []
    for v in (nmea, unknown):
        raw = TYPESTORE.serialize_cdr(ros.gnss_velocity(v, v.sensor_time_ns, "gnss"), ros.TWIST)
        message, why = ros_in.gnss_velocity(TYPESTORE.deserialize_cdr(raw, ros.TWIST), 7)
        assert why == "" and message.sensor_time_ns == v.sensor_time_ns and message.host_mono_ns == 7
        back.append(message)
    assert back[0].velocity_enu_mps == nmea.velocity_enu_mps
    assert back[0].velocity_covariance == nmea.velocity_covariance and back[0].covariance_type == 2
    assert back[1].velocity_enu_mps == unknown.velocity_enu_mps
    assert back[1].velocity_covariance == (0.0,) * 9 and back[1].covariance_type == 0


def test_calibration_and_static_transforms_are_the_recorded_config(round_trip):
    config, back_config = round_trip["config"], round_trip["back_config"]
    assert sorted(c.name for c in back_config.sensors.cameras) == sorted(c.name for c in config.sensors.cameras)
    for cam in back_config.sensors.cameras:
        original = next(c for c in config.sensors.cameras if c.name == cam.name)
        np.testing.assert_allclose(cam.intrinsics.matrix(), original.intrinsics.matrix())
        assert (cam.width, cam.height, cam.distortion) == (original.width, original.height, original.distortion)
        np.testing.assert_allclose(cam.extrinsics.matrix(), original.extrinsics.matrix(), atol=1e-9)
    np.testing.assert_allclose(back_config.sensors.lidar.extrinsics.matrix(), config.sensors.lidar.extrinsics.matrix(),
                               atol=1e-9)
    assert back_config.sensors.gnss.antenna_lever_arm_m == pytest.approx(config.sensors.gnss.antenna_lever_arm_m)
    np.testing.assert_allclose(back_config.sensors.gnss.imu_extrinsics.matrix(),
                               config.sensors.gnss.imu_extrinsics.matrix(), atol=1e-9)
    with AnyReader([round_trip["bag"]], default_typestore=TYPESTORE) as reader:
        conn = [c for c in reader.connections if c.topic == "/tf_static"]
        (_, _, raw), = list(reader.messages(connections=conn))
        transforms = reader.deserialize(raw, conn[0].msgtype).transforms
    expected = sensor_frames(config)
    assert sorted(t.child_frame_id for t in transforms) == sorted(expected)
    for t in transforms:
        assert t.header.frame_id == "base_link"
        np.testing.assert_allclose(matrix(t.transform.translation, t.transform.rotation),
                                   expected[t.child_frame_id].matrix(), atol=1e-12)


def test_lidar_points_are_the_decoded_packets(round_trip):
    original, back, config = round_trip["original"], round_trip["back"], round_trip["config"]
    metadata = configured_decoding(config.sensors.lidar, round_trip["config_path"])
    scans = packet_scans(original[LIDAR_PACKETS], metadata, 1)
    clouds = back[LIDAR_POINTS]
    assert len(clouds) == len(scans.scans) == len(original[LIDAR_PACKETS]) // metadata.packets_per_frame
    for cloud, chunk in zip(clouds, scans.scans, strict=True):
        scan = scans.decode(chunk)
        got = point_array(cloud)
        np.testing.assert_array_equal(got[:, :3], scan.xyz.astype(np.float32))
        np.testing.assert_array_equal(got[:, 3], scan.intensity.astype(np.float32))
        start = int(scan.times_ns.min())
        assert cloud.sensor_time_ns == start  # the Lidar's clock is UTC (PTP) in the simulator
        np.testing.assert_allclose(got[:, 4], ((scan.times_ns - start) * 1e-9)[scan.time_index].astype(np.float32),
                                   rtol=1e-6, atol=1e-9)


def test_poses_come_back_as_odometry(round_trip):
    got, sent = round_trip["back"][POSE], round_trip["poses"]
    offset = utc_minus_mono(round_trip["original"])
    assert [p.sensor_time_ns for p in got] == [p.sensor_time_ns + offset for p in sent]
    np.testing.assert_allclose([p.position_m for p in got], [p.position_m for p in sent], atol=1e-12)
    for p, q in zip(got, sent, strict=True):
        np.testing.assert_allclose(Rotation.from_quat(p.orientation_xyzw).as_matrix(),
                                   Rotation.from_quat(q.orientation_xyzw).as_matrix(), atol=1e-12)
        assert p.frame_id == "enu"


def test_a_bad_input_is_one_error_line_and_no_bag(city_drive, tmp_path, capsys):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a log at all")
    exists = tmp_path / "exists"
    exists.mkdir()
    for logs, out in (([tmp_path / "absent.mcap"], tmp_path / "a"), ([junk], tmp_path / "b"),
                      ([city_drive], exists)):
        assert roadlog(["export", "ros2", *map(str, logs), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("error: ") == 3 and "Traceback" not in err, err
    assert "no such log" in err and "is not an MCAP file" in err and "exists" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists", "junk.mcap"]


def test_a_point_cloud_lidars_scans_come_back_as_they_were(city_drive, tmp_path):
    """A point-cloud Lidar's log (its scans on lidar/points, no packets): each PointCloud is one PointCloud2."""
    from tests.point_cloud_logs import point_cloud_log

    clouds_log = point_cloud_log(city_drive, tmp_path / "clouds.mcap")
    assert roadlog(["export", "ros2", str(clouds_log), "--out", str(tmp_path / "bag")]) == 0
    assert roadlog(["import", "ros2", str(tmp_path / "bag"), "--out", str(tmp_path / "back.mcap")]) == 0
    sent, got = by_topic(clouds_log)[LIDAR_POINTS], by_topic(tmp_path / "back.mcap")[LIDAR_POINTS]
    assert len(got) == len(sent) > 40
    for a, b in zip(got, sent, strict=True):
        assert a.sensor_time_ns == b.sensor_time_ns
        np.testing.assert_array_equal(point_array(a)[:, :4], point_array(b)[:, :4])
        np.testing.assert_allclose(point_array(a)[:, 4], point_array(b)[:, 4], rtol=1e-6, atol=1e-9)


VENDOR_DATA = Path("/work/shared/data/lidar_nebula")


@pytest.mark.skipif(not VENDOR_DATA.is_dir(), reason="shared lidar_nebula captures not present")
def test_a_vendor_lidars_packets_are_exported_as_the_mapper_decodes_them(tmp_path):
    """A VLP-16 capture logged as packets: one PointCloud2 per rotation, the points lidar_ground decodes (read back
    with the importer's PointCloud2 reader; a log of Lidar packets alone has no camera to import a car from)."""
    import yaml

    from daemon.spine.config import load_config
    from daemon.spine.messages import LidarPacket
    from drivers.lidar.pcap_udp import read_pcap_udp
    from importers.ros2_messages import point_cloud
    from mapping.inputs.lidar_ground import lidar_scans

    (tmp_path / "VLP16.yaml").write_bytes((VENDOR_DATA / "calib" / "VLP16.yaml").read_bytes())
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["sensors"]["lidar"] = {"model": "velodyne-vlp16", "metadata_file": "VLP16.yaml",
                                "extrinsics": data["sensors"]["lidar"]["extrinsics"]}
    (tmp_path / "car.yaml").write_text(yaml.safe_dump(data))
    car = load_config(tmp_path / "car.yaml")
    payloads = [d.payload for d in read_pcap_udp(VENDOR_DATA / "velodyne" / "vlp16.pcap").datagrams]
    base = 3600 * 10**9
    packets = [LidarPacket(seq=i, sensor_time_ns=base + int.from_bytes(p[1200:1204], "little") * 1000,
                           host_mono_ns=base + i * 1_000_000, data=p) for i, p in enumerate(payloads)]
    with LogWriter(tmp_path / "vlp16.mcap", car, config_path=tmp_path / "car.yaml", log_time_offset_ns=0) as writer:
        for p in packets:
            writer.write(LIDAR_PACKETS, p)
    assert roadlog(["export", "ros2", str(tmp_path / "vlp16.mcap"), "--out", str(tmp_path / "bag")]) == 0
    with AnyReader([tmp_path / "bag"], default_typestore=TYPESTORE) as reader:
        conns = [c for c in reader.connections if c.topic == "/lidar/points"]
        clouds = [point_cloud(reader.deserialize(raw, c.msgtype), t)[0] for c, t, raw in reader.messages(conns)]
    scans = lidar_scans(packets, [], lambda: configured_decoding(car.sensors.lidar, tmp_path / "car.yaml"), 1)
    assert len(clouds) == len(scans.scans) >= 3
    for cloud, scan in zip(clouds, scans.scans, strict=True):
        points, got = scans.decode(scan), point_array(cloud)
        np.testing.assert_array_equal(got[:, :3], points.xyz)
        np.testing.assert_array_equal(got[:, 3], points.intensity)
        start = int(points.times_ns.min())
        np.testing.assert_allclose(got[:, 4], ((points.times_ns - start) * 1e-9)[points.time_index], rtol=1e-6,
                                   atol=1e-9)


def _bag_messages(bag: Path, topic: str) -> list:
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        conns = [c for c in reader.connections if c.topic == topic]  # none: messages() would give every topic's
        return [(t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages(connections=conns)] \
            if conns else []


def test_a_recorded_logs_live_pose_moves_base_link_on_tf(city_drive, tmp_path, capsys):
    """A log the daemon recorded holds its live pose (`vehicle/pose`, map -> vehicle): the bag has it as /tf
    map -> base_link, so the car moves in RViz or Foxglove, and no Odometry (which the importer would take as the
    drive's given trajectory, the `pose` topic, instead of fusing it from the sensors as the original's
    reconstruction does). Beside a `pose` topic (which gives /odom and /tf) the live pose is listed, not exported."""
    config, config_path = config_from_logs([str(city_drive)])  # with the path, a log records the Lidar's metadata
    # stamped as vehicle_pose stamps them: sensor and host time both the time it is the pose of
    live = [VehiclePose(seq=k, sensor_time_ns=4 * 10**9 + k * 100_000_000, host_mono_ns=4 * 10**9 + k * 100_000_000,
                        frame_id=MAP_FRAME, position_m=(2.0 * k, -0.5 * k, 0.02 * k),
                        orientation_xyzw=tuple(Rotation.from_euler("z", 0.03 * k).as_quat())) for k in range(15)]
    with LogWriter(tmp_path / "live.mcap", config, config_path=config_path, log_time_offset_ns=0) as writer:
        for pose in live:
            writer.write(VEHICLE_POSE, pose)
    assert roadlog(["export", "ros2", str(tmp_path / "live.mcap"), "--out", str(tmp_path / "bag")]) == 0
    tfs = _bag_messages(tmp_path / "bag", "/tf")
    assert [t for t, _ in tfs] == [p.host_mono_ns for p in live]  # no anchors: the host clock (said on stderr)
    assert not _bag_messages(tmp_path / "bag", ODOM_TOPIC)
    for (_, msg), pose in zip(tfs, live, strict=True):
        [tf] = msg.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == (MAP_FRAME, "base_link")
        assert tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec == pose.sensor_time_ns
        expected = np.eye(4)
        expected[:3, :3] = Rotation.from_quat(pose.orientation_xyzw).as_matrix()
        expected[:3, 3] = pose.position_m
        np.testing.assert_allclose(matrix(tf.transform.translation, tf.transform.rotation), expected, atol=1e-12)
    given = [VehiclePose(seq=k, sensor_time_ns=p.sensor_time_ns, host_mono_ns=p.host_mono_ns, frame_id="enu",
                         position_m=p.position_m, orientation_xyzw=p.orientation_xyzw) for k, p in enumerate(live)]
    with LogWriter(tmp_path / "given.mcap", config, config_path=config_path, log_time_offset_ns=0) as writer:
        for pose in given:
            writer.write(POSE, pose)
    capsys.readouterr()
    assert roadlog(["export", "ros2", str(tmp_path / "live.mcap"), str(tmp_path / "given.mcap"),
                    "--out", str(tmp_path / "both")]) == 0
    assert {msg.transforms[0].header.frame_id for _, msg in _bag_messages(tmp_path / "both", "/tf")} == {"enu"}
    assert len(_bag_messages(tmp_path / "both", ODOM_TOPIC)) == len(given)
    assert f"not exported {VEHICLE_POSE}: the `pose` topic gives /odom and /tf ({len(live)})" in \
        capsys.readouterr().err
