"""What the log holds for viewing (mapping/viewing/): the viewing clouds, every vendor's scans decoded by the mapper's
decoders at the configured rate and stamped on the host clock; the live pose, fused from the bus's GNSS, IMU and wheel
speeds as the offline trajectory is; the config keys; and the mapper never counting a viewing cloud beside the packets
it was decoded from, while a log of viewing clouds alone still maps."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.log_format.reader import read_log
from daemon.log_format.static_transforms import LIDAR_FRAME
from daemon.log_format.writer import LogWriter
from daemon.spine.config import ConfigError, load_config, parse_config
from daemon.spine.messages import LidarPacket
from daemon.spine.point_cloud_codec import point_array
from daemon.spine.process_table import process_table
from daemon.spine.topics import (
    GNSS_FIX,
    IMU,
    LIDAR_PACKETS,
    LIDAR_VIEW,
    MAP_FRAME,
    TIME_ANCHOR,
    VEHICLE_POSE,
    WHEEL_SPEEDS,
    topic_table,
)
from drivers.lidar.pcap_udp import read_pcap_udp
from mapping.inputs.drive_inputs import fuse_log_trajectory, load_drive
from mapping.inputs.lidar_ground import configured_decoding, lidar_scans
from mapping.localization.sensor_time import fit_clocks
from mapping.offline.reconstruct_command import config_from_logs
from mapping.viewing.lidar_view import ViewingClouds
from mapping.viewing.vehicle_pose import LivePose
from tests.conftest import REPO

VENDOR_DATA = Path("/work/shared/data/lidar_nebula")
VENDOR_CAPTURES = {  # capture: (model, calibration)
    "velodyne/vlp16.pcap": ("velodyne-vlp16", "VLP16.yaml"),
    "velodyne/vlp32.pcap": ("velodyne-vlp32c", "VLP32.yaml"),
    "velodyne/vls128.pcap": ("velodyne-vls128", "VLS128.yaml"),
    "hesai/40p.pcap": ("hesai-pandar40p", "Pandar40P.csv"),
    "hesai/64.pcap": ("hesai-pandar64", "Pandar64.csv"),
    "hesai/qt128.pcap": ("hesai-pandarqt128", "PandarQT128.csv"),
    "hesai/xt32.pcap": ("hesai-pandarxt32", "PandarXT32.csv"),
    "robosense/helios16P.pcap": ("robosense-helios16p", "RobosenseHelios16P.csv"),
}


def drive_messages(log: Path, topics: set[str]) -> list[tuple[str, object]]:
    return [(rec.topic, rec.message) for rec in read_log([log], topics=topics)]


def cloud_latency(cloud, points) -> int:
    """The viewing cloud holds the scan's points with a return, as the mapper decodes them, each at its firing time
    moved onto the host clock by one latency (returned)."""
    returned = np.any(points.xyz != 0, axis=1)
    got = point_array(cloud)
    np.testing.assert_array_equal(got[:, :3], points.xyz[returned])
    fired = points.times_ns[points.time_index[returned]]
    assert cloud.sensor_time_ns == cloud.host_mono_ns
    np.testing.assert_allclose(got[:, 4], (fired - fired.min()) / 1e9, atol=2e-6)
    assert cloud.sensor == LIDAR_FRAME
    return int(cloud.sensor_time_ns - fired.min())


def test_an_ousters_viewing_clouds_are_every_fifth_scan_as_the_mapper_decodes_it(city_drive):
    config, config_path = config_from_logs([str(city_drive)])
    assert config.recorder.point_cloud_view_hz == 2.0 and config.sensors.lidar.rate_hz == 10  # the defaults
    decoding = configured_decoding(config.sensors.lidar, config_path)
    packets = [m for _, m in drive_messages(city_drive, {LIDAR_PACKETS})]
    viewer = ViewingClouds(decoding, 2.0, 10)
    clouds = [c for c in map(viewer.take, packets) if c is not None]
    scans = lidar_scans(packets, [], lambda: decoding, 1)
    full = len(packets) // decoding.packets_per_frame  # the last scan is finished by the next packet: never seen
    assert viewer.scans == full - (len(packets) % decoding.packets_per_frame == 0)
    assert len(clouds) == viewer.viewed == len(range(0, viewer.scans, 5)) and viewer.undecodable == 0
    for k, cloud in zip(range(0, viewer.scans, 5), clouds, strict=True):
        scan_packets = scans.scans[k]
        # the smallest (arrival - stamp) of the scans up to this one
        seen = packets[:(k + 1) * decoding.packets_per_frame]
        assert cloud_latency(cloud, scans.decode(scan_packets)) == min(
            int(p.host_mono_ns) - int(p.sensor_time_ns) for p in seen)
        # on the host clock: the scan's packets arrived from its first point on
        assert 0 <= scan_packets[0].host_mono_ns - cloud.sensor_time_ns < 50_000_000
    gaps = np.diff([c.sensor_time_ns for c in clouds]) / 1e9
    assert np.all(np.abs(gaps - 0.5) < 0.01), gaps


@pytest.mark.skipif(not VENDOR_DATA.is_dir(), reason="shared lidar_nebula captures not present")
@pytest.mark.parametrize("capture", sorted(VENDOR_CAPTURES))
def test_every_vendors_viewing_clouds_are_its_scans_as_the_mapper_decodes_them(tmp_path, capture):
    model, calibration = VENDOR_CAPTURES[capture]
    (tmp_path / calibration).write_bytes((VENDOR_DATA / "calib" / calibration).read_bytes())
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["sensors"]["lidar"] = {"model": model, "metadata_file": calibration,
                                "extrinsics": data["sensors"]["lidar"]["extrinsics"]}
    (tmp_path / "car.yaml").write_text(yaml.safe_dump(data))
    lidar = load_config(tmp_path / "car.yaml").sensors.lidar
    decoding = configured_decoding(lidar, tmp_path / "car.yaml")
    payloads = [d.payload for d in read_pcap_udp(VENDOR_DATA / capture).datagrams]
    stamps = decoding.new_decoder().check(payloads).sensor_time_ns  # as the vendor driver stamps them
    base = 3600 * 10**9
    packets = [LidarPacket(seq=i, sensor_time_ns=base + int(t), host_mono_ns=base + int(t) + 2_000_000, data=p)
               for i, (t, p) in enumerate(zip(stamps, payloads, strict=True)) if t]
    viewer = ViewingClouds(decoding, 1000.0, lidar.rate_hz)  # every scan, however short (the first)
    clouds = [c for c in map(viewer.take, copy.deepcopy(packets)) if c is not None]
    scans = lidar_scans(packets, [], lambda: decoding, 1)
    assert viewer.undecodable == 0 and len(clouds) == len(scans.scans) - 1 >= 1  # the last scan is never ended
    for cloud, scan in zip(clouds, scans.scans, strict=False):
        assert cloud_latency(cloud, scans.decode(scan)) == 2_000_000


def test_a_scan_that_does_not_decode_is_counted_and_skipped(city_drive):
    config, config_path = config_from_logs([str(city_drive)])
    decoding = configured_decoding(config.sensors.lidar, config_path)
    packets = [m for _, m in drive_messages(city_drive, {LIDAR_PACKETS})][:3 * decoding.packets_per_frame + 1]
    for p in packets[:decoding.packets_per_frame]:
        p.data = bytes(p.data)[:100]  # torn: not a packet of this layout
    viewer = ViewingClouds(decoding, 10, 10)
    clouds = [c for c in map(viewer.take, packets) if c is not None]
    assert viewer.scans == 3 and viewer.viewed == len(clouds) == 2
    report = viewer.report()
    assert report["undecodable"] + report["without_points"] == 1, report


def test_the_live_pose_follows_the_offline_trajectory_at_its_rate(city_drive):
    config, _ = config_from_logs([str(city_drive)])
    assert config.recorder.pose_hz == 10.0
    messages = drive_messages(city_drive, {GNSS_FIX, IMU, WHEEL_SPEEDS, TIME_ANCHOR})
    live = LivePose(config)
    assert live.report()["map_origin"] is None
    poses = []
    for topic, msg in messages:
        live.take(topic, msg)
        poses += live.poses()
    first_fix = next(m for t, m in messages if t == GNSS_FIX)  # the map frame's origin, in every health report
    assert live.report()["map_origin"] == {"lat_deg": first_fix.latitude_deg, "lon_deg": first_fix.longitude_deg,
                                           "alt_m": first_fix.altitude_m}
    assert live.failed == 0 and live.fusions >= 3
    assert (messages[-1][1].host_mono_ns - poses[-1].sensor_time_ns) / 1e9 > 0.2  # the newest wait for more data
    poses += live.poses(final=True)  # at the stop: the rest, to the data's end
    times = np.array([p.sensor_time_ns for p in poses])
    assert np.all(np.diff(times) == 100_000_000) and np.all(times % 100_000_000 == 0)
    assert all(p.host_mono_ns == p.sensor_time_ns and p.frame_id == MAP_FRAME for p in poses)
    by = {t: [m for tp, m in messages if tp == t] for t in (GNSS_FIX, IMU, WHEEL_SPEEDS)}
    anchors = [(m.host_mono_ns, m.utc_ns) for tp, m in messages if tp == TIME_ANCHOR]
    clocks = fit_clocks(by, anchors)
    offline = fuse_log_trajectory(by[GNSS_FIX], by[IMU], by[WHEEL_SPEEDS], config, live.origin, clocks)
    positions, _ = offline.interpolate(times)
    error = np.linalg.norm(np.array([p.position_m for p in poses]) - positions, axis=1)
    assert error.max() < 0.5, error.max()
    moved = np.linalg.norm(np.subtract(poses[-1].position_m, poses[0].position_m))
    assert moved > 0.5 * (times[-1] - times[0]) / 1e9  # the city drive goes at ~9 m/s
    assert (offline.times_ns[-1] - times[-1]) / 1e9 < 0.1  # to within a pose of the data's end


def test_the_viewing_keys_are_validated_and_switch_their_processes(tmp_path):
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    for bad in ({"point_cloud_view_hz": 15}, {"point_cloud_view_hz": -1}, {"pose_hz": 51}, {"pose_hz": "often"}):
        broken = copy.deepcopy(data)
        broken["recorder"].update(bad)
        with pytest.raises(ConfigError, match="point_cloud_view_hz|pose_hz"):
            parse_config(broken)
    config = parse_config(data)
    names = {spec.name for spec in process_table(config, "car.yaml", "live")}
    assert {"lidar_view", "vehicle_pose"} <= names and {LIDAR_VIEW, VEHICLE_POSE} <= set(topic_table(config))
    replay = process_table(config, "car.yaml", "replay", replay_logs=("a.mcap",))
    assert {"lidar_view", "vehicle_pose"} <= set(next(s for s in replay if s.name == "replay").start_after)
    assert not {"lidar_view", "vehicle_pose"} & {s.name for s in process_table(config, "c", "live", record=False)}
    data["recorder"].update(point_cloud_view_hz=0, pose_hz=0)
    off = parse_config(data)
    assert not {"lidar_view", "vehicle_pose"} & {spec.name for spec in process_table(off, "car.yaml", "live")}
    assert not {LIDAR_VIEW, VEHICLE_POSE} & set(topic_table(off))


def test_the_mapper_takes_viewing_clouds_only_from_a_log_without_packets(city_drive, tmp_path):
    """Beside the packets they were decoded from, viewing clouds are not read as scans (no scan counted twice); a log
    whose Lidar record is its viewing clouds alone maps its ground from them."""
    config, config_path = config_from_logs([str(city_drive)])
    decoding = configured_decoding(config.sensors.lidar, config_path)
    records = list(read_log([city_drive]))
    viewer = ViewingClouds(decoding, 2.0, 10)
    views = [c for c in (viewer.take(r.message) for r in records if r.topic == LIDAR_PACKETS) if c is not None]
    both, alone = tmp_path / "both.mcap", tmp_path / "alone.mcap"
    for path, keep_packets in ((both, True), (alone, False)):
        stream = [(r.message.host_mono_ns, r.topic, r.message) for r in records
                  if keep_packets or r.topic != LIDAR_PACKETS]
        stream += [(c.host_mono_ns, LIDAR_VIEW, c) for c in views]
        with LogWriter(path, config, config_path=config_path, log_time_offset_ns=0) as writer:
            for _, topic, msg in sorted(stream, key=lambda s: s[0]):
                writer.write(topic, msg)
    with_packets = load_drive([both], config, config_path)
    original = load_drive([city_drive], config, config_path)
    assert with_packets.counts.get("lidar_view_clouds") is None
    assert with_packets.counts["lidar_packets"] == original.counts["lidar_packets"]
    np.testing.assert_array_equal(with_packets.lidar_ground_points, original.lidar_ground_points)
    only_views = load_drive([alone], config, config_path)
    assert only_views.counts["lidar_view_clouds"] == len(views) and "lidar_packets" not in only_views.counts
    assert len(only_views.lidar_ground_points) > 1000
