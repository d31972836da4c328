"""`roadlog simulate` end to end: the drive log holds every sensor topic in host arrival order with
per-topic sequence numbers, the ground truth beside it agrees with the logged sensors, and live mode plays
the log into a real UDP socket, a pseudo-terminal and a udp_multicast CAN bus."""

import os
import random
import select
import socket
import threading
from collections import Counter
from pathlib import Path

import can
import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from daemon.log_format.reader import read_log, read_metadata
from daemon.spine.config import load_config
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import GnssFix, GnssVelocity, ImuSample
from daemon.spine.topics import (
    CAN_FRAMES,
    GNSS_FIX,
    GNSS_VELOCITY,
    IMU,
    LIDAR_IMU,
    LIDAR_PACKETS,
    TIME_ANCHOR,
    WHEEL_SPEEDS,
    camera_topic,
    mask_topic,
)
from drivers.gnss.gnss_messages import GnssDecoder
from drivers.gnss.stream_framer import StreamFramer
from drivers.lidar.ouster_encoder import packet_frame_id
from drivers.lidar.ouster_metadata import parse_metadata
from drivers.lidar.ouster_packet_layout import packet_layout
from sim.drive_log import main as simulate_main
from sim.live_drive import open_gnss_pty, run_live_drive

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
CONFIG = load_config(CONFIGS / "sim.yaml")
SECONDS = 1.5


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "city.mcap"
    assert simulate_main(["--scenario", "city", "--seconds", str(SECONDS), "--out", str(out)]) == 0
    return out


def _gt_at(gt, x, y, name):
    j = ((x - gt["grid_origin_xy"][0]) / gt["grid_resolution_m"]).astype(int)
    i = ((y - gt["grid_origin_xy"][1]) / gt["grid_resolution_m"]).astype(int)
    return gt[name][i, j]


def test_drive_log_is_complete_ordered_and_decodable(drive):
    records = list(read_log([drive]))
    counts = Counter(r.topic for r in records)
    for cam in CONFIG.sensors.cameras:
        assert counts[camera_topic(cam.name)] == counts[mask_topic(cam.name)] == pytest.approx(15, abs=1)
    assert counts[LIDAR_PACKETS] == pytest.approx(SECONDS * 640, rel=0.1)
    assert counts[GNSS_FIX] == pytest.approx(SECONDS * 10, abs=2)
    assert counts[IMU] == counts[LIDAR_IMU] == pytest.approx(SECONDS * 100, abs=2)  # the GNSS's and the Lidar's
    lidar_imu = [r.message for r in records if r.topic == LIDAR_IMU]
    assert 9.0 < np.mean([np.linalg.norm(m.accel_mps2) for m in lidar_imu]) < 10.6  # gravity and a bit of motion
    lidar_stamps = [r.message.sensor_time_ns for r in records if r.topic == LIDAR_PACKETS]
    assert abs(lidar_imu[0].sensor_time_ns - lidar_stamps[0]) < 1_000_000_000  # on the Lidar's clock
    assert counts[CAN_FRAMES] == 2 * counts[WHEEL_SPEEDS] == pytest.approx(SECONDS * 100, abs=2)
    assert counts[TIME_ANCHOR] >= 2
    times = [r.log_time_ns for r in records]
    assert times == sorted(times)
    for topic in counts:
        seqs = [r.message.seq for r in records if r.topic == topic]
        assert seqs == list(range(len(seqs))), topic
    for r in records:
        if r.topic.startswith("camera/"):
            cam = CONFIG.camera(r.topic.split("/")[1])
            image = cv2.imdecode(np.frombuffer(r.message.data, np.uint8), cv2.IMREAD_COLOR)
            assert image.shape == (cam.height, cam.width, 3)
            assert r.message.host_mono_ns - r.message.sensor_time_ns > 10_000_000  # delivery latency
        elif r.topic.startswith("mask/"):
            mask = cv2.imdecode(np.frombuffer(r.message.data, np.uint8), cv2.IMREAD_UNCHANGED)
            assert mask.ndim == 2 and set(np.unique(mask)) <= set(range(6))
        elif r.topic == LIDAR_PACKETS:
            assert len(r.message.data) == 24896
    meta = read_metadata(drive)["roadlog"]
    assert meta["scenario"] == "city" and meta["ground_truth"] == "city.gt.npz"


def test_ground_truth_agrees_with_the_logged_sensors(drive):
    gt = np.load(drive.with_name("city.gt.npz"))
    pos = gt["trajectory_position_enu"]
    assert len(pos) == pytest.approx(SECONDS * 200, abs=2)
    assert gt["trajectory_quaternion_xyzw"].shape == (len(pos), 4)
    # The reference point rides reference_height_m above the surface.
    ground = _gt_at(gt, pos[:, 0], pos[:, 1], "elevation")
    np.testing.assert_allclose(pos[:, 2] - ground, CONFIG.vehicle.reference_height_m, atol=0.02)
    # Lidar road points lie on the ground-truth elevation.
    pts = gt["lidar_points_enu"]
    assert len(pts) > 10000
    z = _gt_at(gt, pts[:, 0], pts[:, 1], "elevation")
    assert np.nanpercentile(np.abs(pts[:, 2] - z), 95) < 0.03
    # The logged GNSS fixes are the antenna, centimetre-close (RTK), at the trajectory's times.
    lat, lon, alt = gt["enu_origin_lat_lon_alt"]
    frame = LocalFrame(float(lat), float(lon), float(alt))
    lever = np.array(CONFIG.sensors.gnss.antenna_lever_arm_m)
    utc0, host0 = int(gt["utc_start_ns"]), int(gt["host_mono_at_start_ns"])
    fixes = [r.message for r in read_log([drive], topics=[GNSS_FIX])]
    for fix in fixes:
        t_host = fix.sensor_time_ns - utc0 + host0
        k = np.searchsorted(gt["trajectory_host_mono_ns"], t_host)
        rot = Rotation.from_quat(gt["trajectory_quaternion_xyzw"][k]).as_matrix()
        antenna = gt["trajectory_position_enu"][k] + rot @ lever
        enu = frame.geodetic_to_enu(fix.latitude_deg, fix.longitude_deg, fix.altitude_m)
        assert np.linalg.norm(enu - antenna) < 0.12  # cm noise plus up to 5 ms of sampling (5 cm at 10 m/s)
    # ... and their velocities the antenna's (the turn's share included), within the receiver's reported accuracy
    times = gt["trajectory_host_mono_ns"]
    rotations = Rotation.from_quat(gt["trajectory_quaternion_xyzw"]).as_matrix()
    antenna_track = gt["trajectory_position_enu"] + rotations @ lever
    velocities = [r.message for r in read_log([drive], topics=[GNSS_VELOCITY])]
    assert [v.sensor_time_ns for v in velocities] == [f.sensor_time_ns for f in fixes]
    errors = []
    for v in velocities:
        k = np.searchsorted(times, v.sensor_time_ns - utc0 + host0)
        true = (antenna_track[k + 1] - antenna_track[k - 1]) / ((times[k + 1] - times[k - 1]) / 1e9)
        errors.append(np.array(v.velocity_enu_mps) - true)
        assert v.covariance_type == 2
    sigma = np.sqrt(velocities[0].velocity_covariance[0])
    assert np.sqrt(np.mean(np.square(errors))) < 2 * sigma, (np.sqrt(np.mean(np.square(errors))), sigma)
    speeds = [r.message for r in read_log([drive], topics=[WHEEL_SPEEDS])]
    assert np.mean([s.rear_left_mps for s in speeds]) == pytest.approx(10.0, abs=1.0)


def play_live(drive, with_can: bool = False, **kwargs):
    """`run_live_drive` into a real UDP socket, a pty (and CAN on udp_multicast): its stats and what came out
    (datagrams, the serial bytes, CAN frames)."""
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 32 * 1024 * 1024)
    receiver.bind(("127.0.0.1", 0))
    pty = open_gnss_pty()
    reader = os.open(pty.path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    tx = rx = None
    if with_can:
        group, port = "239.74.163.77", random.randrange(40000, 60000)
        tx = can.Bus(interface="udp_multicast", channel=group, port=port)
        rx = can.Bus(interface="udp_multicast", channel=group, port=port)
    stop = threading.Event()
    result = {}
    packets, serial, frames = [], bytearray(), []

    def play():
        result["stats"] = run_live_drive(drive, lidar_address=receiver.getsockname(), gnss_fd=pty.master_fd,
                                         can_bus=tx, stop=stop, **kwargs)

    player = threading.Thread(target=play)
    player.start()
    try:
        while player.is_alive() or select.select([receiver, reader], [], [], 0.3)[0]:
            ready, _, _ = select.select([receiver, reader], [], [], 0.05)
            if receiver in ready:
                packets.append(receiver.recv(65536))
            if reader in ready:
                serial += os.read(reader, 65536)
            while rx is not None and (msg := rx.recv(0)) is not None:
                frames.append(msg)
        player.join(10)
    finally:
        stop.set()
        for bus in (tx, rx):
            if bus is not None:
                bus.shutdown()
        os.close(reader)
        pty.close()
        receiver.close()
    return result["stats"], packets, serial, frames


def test_live_mode_plays_the_drive_into_udp_pty_and_can(drive):
    stats, packets, serial, frames = play_live(drive, with_can=True, rate=2.0)
    logged = Counter(r.topic for r in read_log([drive], topics=[LIDAR_PACKETS, CAN_FRAMES, GNSS_FIX]))
    assert stats.errors == 0 and stats.gnss_dropped_bytes == 0
    assert stats.lidar_packets == logged[LIDAR_PACKETS] and len(packets) > 0.95 * logged[LIDAR_PACKETS]
    assert all(len(p) == 24896 for p in packets)
    assert len(frames) > 0.9 * logged[CAN_FRAMES]
    decoder = GnssDecoder("nmea+ubx")
    out = [m for f in StreamFramer().feed(bytes(serial)) for m in decoder.decode(f, 0)]
    fixes = [m for m in out if isinstance(m, GnssFix)]
    assert len(fixes) >= logged[GNSS_FIX] - 1
    logged_fixes = [r.message for r in read_log([drive], topics=[GNSS_FIX])]
    assert fixes[0].latitude_deg == pytest.approx(logged_fixes[0].latitude_deg, abs=1e-8)
    assert sum(isinstance(m, ImuSample) for m in out) == pytest.approx(SECONDS * 100, abs=3)
    # each fix's velocity is the one logged for its epoch (to the receiver's mm/s)
    logged_velocities = {v.sensor_time_ns: v for v in (r.message for r in read_log([drive], topics=[GNSS_VELOCITY]))}
    velocities = [m for m in out if isinstance(m, GnssVelocity)]
    assert len(velocities) >= len(logged_velocities) - 1
    for v in velocities:
        assert v.velocity_enu_mps == pytest.approx(logged_velocities[v.sensor_time_ns].velocity_enu_mps, abs=1e-3)


def test_a_drive_without_masks_has_the_same_frames_and_no_mask_topic(city_drive, city_drive_without_masks):
    with_masks = [(r.topic, r.log_time_ns, bytes(r.message.data)) for r in read_log([city_drive])
                  if r.topic.startswith("camera/")]
    records = list(read_log([city_drive_without_masks]))
    without = [(r.topic, r.log_time_ns, bytes(r.message.data)) for r in records if r.topic.startswith("camera/")]
    assert len(without) == 150 and without == with_masks  # the same images at the same times
    assert not any(r.topic.startswith("mask/") for r in records)
    assert {r.topic for r in records if not r.topic.startswith("camera/")} == \
        {r.topic for r in read_log([city_drive]) if not r.topic.startswith(("camera/", "mask/"))}


def test_a_looped_live_drive_carries_the_sensors_numbering_and_clocks_on(drive):
    """Two passes: every Lidar frame id once (the second pass's numbered on from the first's), the packets' column
    times and the GNSS epochs one drive length later, so a driver sees one endless drive."""
    layout = packet_layout(parse_metadata(CONFIGS / CONFIG.sensors.lidar.metadata_file))
    stats, packets, serial, _ = play_live(drive, passes=2, lidar_layout=layout)
    logged = [r.message for r in read_log([drive], topics=[LIDAR_PACKETS])]
    assert stats.passes == 2 and stats.errors == 0 and stats.lidar_packets == 2 * len(logged)
    frames_per_pass = len({packet_frame_id(bytes(p.data), layout) for p in logged})
    ids = Counter(packet_frame_id(p, layout) for p in packets)
    first = packet_frame_id(bytes(logged[0].data), layout)
    assert set(ids) <= set(range(first, first + 2 * frames_per_pass)) and max(ids.values()) <= len(logged) // \
        frames_per_pass  # no frame id twice: the second pass numbered on
    assert len(packets) > 0.95 * 2 * len(logged) and first + 2 * frames_per_pass - 1 in ids
    column_time = {(packet_frame_id(p, layout), int.from_bytes(p[8:10], "little")): int.from_bytes(p[:8], "little")
                   for p in packets}  # (frame, first measurement id) -> its first column's time
    period_ns = int(SECONDS * 1e9)
    shifted = [(column_time[(f + frames_per_pass, m)] - t) for (f, m), t in column_time.items()
               if (f + frames_per_pass, m) in column_time]
    assert shifted and set(shifted) == {period_ns}
    fixes = [m for f in StreamFramer().feed(bytes(serial)) for m in GnssDecoder("nmea+ubx").decode(f, 0)
             if isinstance(m, GnssFix)]
    times = [f.sensor_time_ns for f in fixes]
    logged_fixes = sum(1 for _ in read_log([drive], topics=[GNSS_FIX]))
    assert len(fixes) >= 2 * logged_fixes - 2 and np.all(np.diff(times) > 0)  # (the receiver's first may be cut)
