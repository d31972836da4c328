"""The vendor Lidar driver (drivers.lidar.vendor_udp_driver) on the real VLP-16 and VLS-128 captures sent through a
real UDP socket to the real process, read back from the real bus; foreign datagrams counted and skipped; the
Velodyne's past-the-hour stamps unwrapped; the mapper's decoding of the published packets (lidar_ground) equal to
decoding the capture directly."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.bus import pubsub
from daemon.commands.check_config import main as check_config_main
from daemon.spine.config import EXIT_CONFIG_ERROR, load_config
from daemon.spine.messages import LidarPacket
from daemon.spine.topics import LIDAR_PACKETS, health_topic
from drivers.lidar.lidar_models import VENDOR_LIDARS
from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.vendor_udp_driver import StampClock
from mapping.inputs.lidar_ground import configured_decoding, lidar_scans

ROOT = Path(__file__).resolve().parents[2]
DATA = Path("/work/shared/data/lidar_nebula")
HOUR_NS = 3600 * 10**9
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared lidar_nebula captures not present")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def vendor_config(tmp_path: Path, model: str, calibration: str, **lidar: object) -> Path:
    """sim.yaml with this Lidar (its calibration copied beside it), a unique bus, a free port."""
    (tmp_path / calibration).write_bytes((DATA / "calib" / calibration).read_bytes())
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"]["shm_prefix"] = f"t{uuid.uuid4().hex[:12]}"
    data["sensors"]["lidar"] = {"model": model, "metadata_file": calibration, "port": free_udp_port(),
                                "extrinsics": data["sensors"]["lidar"]["extrinsics"], **lidar}
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def capture(name: str, vendor: str = "velodyne") -> list[bytes]:
    return [d.payload for d in read_pcap_udp(DATA / vendor / f"{name}.pcap").datagrams]


def run_driver(config_path: Path, datagrams: list[bytes], expected: int) -> tuple[list, str, dict]:
    """The driver process fed `datagrams` over UDP: the packets it published, its stderr and its last health."""
    car = load_config(config_path)
    proc = subprocess.Popen([sys.executable, "-m", "drivers.lidar.vendor_udp_driver", "--config", str(config_path)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        health = pubsub.open_subscriber(car, health_topic("lidar"), start="oldest", wait_s=20)
        assert health.read(timeout_s=20) is not None, "no health: the driver did not start"
        packets = pubsub.open_subscriber(car, LIDAR_PACKETS, start="oldest", wait_s=5)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for k, d in enumerate(datagrams):
                s.sendto(d, ("127.0.0.1", car.sensors.lidar.port))
                if k % 50 == 49:
                    time.sleep(0.005)  # ~10,000 datagrams/s: what the sensors send, not a flood
        got, deadline = [], time.monotonic() + 20
        while len(got) < expected and time.monotonic() < deadline:
            msg = packets.read(timeout_s=0.2, copy=True)
            if msg is not None:
                got.append(msg)
        time.sleep(1.2)  # one more health period: the rejects of the last batch are in it
        last = None
        while (msg := health.read(timeout_s=0.1)) is not None:
            last = msg
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=15)
    assert proc.returncode == 0, err
    return got, err, last


def test_a_velodyne_capture_through_the_driver_process_comes_out_packet_for_packet(tmp_path):
    payloads = capture("vlp16")
    junk = [b"\x00" * 512,  # a position packet on the data port
            payloads[3][:700],  # truncated
            payloads[4] + b"\x00" * 600,  # too long
            bytes(np.random.default_rng(1).integers(0, 256, 1206, dtype=np.uint8)),  # noise of the right size
            b"x" * 1600]  # beyond an Ethernet payload
    datagrams = payloads[:100] + junk + payloads[100:]
    config = vendor_config(tmp_path, "velodyne-vlp16", "VLP16.yaml")
    got, err, health = run_driver(config, datagrams, len(payloads))
    assert [bytes(p.data) for p in got] == payloads  # every data packet, in order, byte for byte
    detail = health.detail
    assert health.rejected == len(junk) and health.published == len(payloads), detail
    assert "wrong_size" in detail and "VLP-16" in detail and "too_large=2" in detail, detail  # 1,806 and 1,600 B
    stamps = np.array([int.from_bytes(p[1200:1204], "little") for p in payloads], np.int64) * 1000
    times = np.array([p.sensor_time_ns for p in got], np.int64)
    np.testing.assert_array_equal(np.diff(times), np.diff(stamps))  # continuous, on the sensor's clock
    assert np.all((times - stamps) % HOUR_NS == 0)  # in whole hours from the packet's stamp ...
    assert abs(times[0] - time.time_ns()) < HOUR_NS  # ... in the host's hour
    assert "Traceback" not in err


def test_a_hesai_capture_through_the_driver_process_comes_out_packet_for_packet(tmp_path):
    """The same driver with another vendor's decoder: a PandarXT32's packets, stamped in UTC (no unwrapping)."""
    payloads = capture("xt32", "hesai")[:600]
    datagrams = payloads[:300] + [payloads[5][:500], capture("vlp16")[0]] + payloads[300:]  # truncated, foreign
    config = vendor_config(tmp_path, "hesai-pandarxt32", "PandarXT32.csv")
    got, err, health = run_driver(config, datagrams, len(payloads))
    assert [bytes(p.data) for p in got] == payloads, err
    assert health.rejected == 2 and "hesai-pandarxt32" in health.detail, health.detail
    check = configured_decoding(load_config(config).sensors.lidar, config).new_decoder().check(payloads)
    np.testing.assert_array_equal([p.sensor_time_ns for p in got], check.sensor_time_ns)


def test_a_pandar128e4x_s_imu_readings_come_out_on_lidar_imu_once_each(tmp_path):
    """Self-made 128E4X packets (tests/drivers/hesai_test_packets.py: from the manual's layout, no capture here)
    whose tails carry an IMU reading updated every 4th packet: each reading is published once, at its packet's
    time, in SI units."""
    from daemon.spine.topics import LIDAR_IMU
    from tests.drivers.hesai_test_packets import encode_128e4x

    rng = np.random.default_rng(2)
    packets = []
    for k in range(200):
        reading = k // 4
        imu = (1000, 1000, 1000 + reading, (reading, -2, 1000), (5, 0, -reading))  # units: 1 mg and 10 mdps
        packets.append(encode_128e4x((k * 20 % 36000, k * 20 % 36000), rng.integers(100, 5000, (2, 128)),
                                     rng.integers(0, 255, (2, 128)), 1_700_000_000 + k // 100, (k % 100) * 10_000,
                                     imu=imu))
    config = vendor_config(tmp_path, "hesai-pandar128e4x", "Pandar128E4X.csv")
    car = load_config(config)
    imu_sub = None
    proc = subprocess.Popen([sys.executable, "-m", "drivers.lidar.vendor_udp_driver", "--config", str(config)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        health = pubsub.open_subscriber(car, health_topic("lidar"), start="oldest", wait_s=20)
        assert health.read(timeout_s=20) is not None
        imu_sub = pubsub.open_subscriber(car, LIDAR_IMU, start="oldest", wait_s=5)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for k, p in enumerate(packets):
                s.sendto(p, ("127.0.0.1", car.sensors.lidar.port))
                if k % 20 == 19:
                    time.sleep(0.01)  # several batches: a reading may straddle two
        samples, deadline = [], time.monotonic() + 10
        while len(samples) < 50 and time.monotonic() < deadline:
            msg = imu_sub.read(timeout_s=0.2, copy=True)
            if msg is not None:
                samples.append(msg)
        time.sleep(0.5)
        extra = imu_sub.read(timeout_s=0.2, copy=True)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=15)
    assert len(samples) == 50 and extra is None  # 200 packets, a reading per 4
    np.testing.assert_allclose([s.accel_mps2[0] for s in samples], np.arange(50) * 1e-3 * 9.80665, atol=1e-9)
    np.testing.assert_allclose([s.accel_mps2[2] for s in samples], 9.80665, rtol=1e-9)  # 1000 mg
    np.testing.assert_allclose([s.gyro_rps[2] for s in samples], -np.radians(np.arange(50) * 0.01), atol=1e-12)
    expected_ns = [(1_700_000_000 + (4 * r) // 100) * 10**9 + ((4 * r) % 100) * 10**7 for r in range(50)]
    assert [s.sensor_time_ns for s in samples] == expected_ns  # the first packet carrying each reading


def test_a_robosense_capture_through_the_driver_process_comes_out_packet_for_packet(tmp_path):
    """A Helios-16P's MSOP packets, its one device-info packet on the data port counted and skipped."""
    datagrams = capture("helios16P", "robosense")
    config = vendor_config(tmp_path, "robosense-helios16p", "RobosenseHelios16P.csv")
    decoder = configured_decoding(load_config(config).sensors.lidar, config).new_decoder()
    check = decoder.check(datagrams)
    payloads = [d for d, ok in zip(datagrams, check.accepted, strict=True) if ok]
    assert check.counts == {"difop": 1} and len(payloads) == len(datagrams) - 1
    got, err, health = run_driver(config, datagrams, len(payloads))
    assert [bytes(p.data) for p in got] == payloads, err
    assert health.rejected == 1 and "difop=1" in health.detail, health.detail
    np.testing.assert_array_equal([p.sensor_time_ns for p in got], check.sensor_time_ns[check.accepted])
    scans = lidar_scans(got, [], lambda: configured_decoding(load_config(config).sensors.lidar, config), 1)
    whole = decoder.decode(payloads)
    np.testing.assert_array_equal(np.concatenate([scans.decode(s).xyz for s in scans.scans]), whole.xyz)


def test_stamps_past_the_hour_are_unwrapped_into_one_time():
    clock = StampClock(HOUR_NS)
    host = 5 * HOUR_NS + HOUR_NS - 1_000_000_000  # 1 s before the top of host hour 6
    before = clock.times(np.array([HOUR_NS - 2_000_000_000, HOUR_NS - 1_000_000]), host)
    after = clock.times(np.array([500_000, 400_000_000]), host)
    np.testing.assert_array_equal(before, [6 * HOUR_NS - 2_000_000_000, 6 * HOUR_NS - 1_000_000])
    np.testing.assert_array_equal(after, [6 * HOUR_NS + 500_000, 6 * HOUR_NS + 400_000_000])
    back = clock.times(np.array([300_000_000]), host)  # a reordered packet goes back, not an hour forward
    assert back[0] == 6 * HOUR_NS + 300_000_000
    utc = StampClock(None)
    np.testing.assert_array_equal(utc.times(np.array([7, 5]), host), [7, 5])


def test_the_mapper_decodes_published_packets_as_the_decoder_decodes_the_capture(tmp_path):
    """VLS-128 (its rotation rate comes from the packet before): scans of the published packets, each decoded with
    the packet before it as lead, give exactly the points of the whole capture decoded at once, each at its
    packet's message time plus its firing offset."""
    payloads = capture("vls128")
    config_path = vendor_config(tmp_path, "velodyne-vls128", "VLS128.yaml")
    car = load_config(config_path)
    decoding = configured_decoding(car.sensors.lidar, config_path)
    base = 7 * HOUR_NS  # the driver's unwrapped times: the stamps placed in some hour
    stamps = np.array([int.from_bytes(p[1200:1204], "little") for p in payloads], np.int64) * 1000
    packets = [LidarPacket(seq=i, sensor_time_ns=int(base + s), host_mono_ns=i, data=p)
               for i, (p, s) in enumerate(zip(payloads, stamps, strict=True))]
    scans = lidar_scans(packets, [], lambda: decoding, 1)
    assert 3 <= len(scans.scans) <= 5  # ~3.6 rotations at 10 Hz
    whole = decoding.new_decoder().decode(payloads)
    xyz, times = [], []
    for scan in scans.scans:
        points = scans.decode(scan)
        xyz.append(points.xyz)
        times.append(points.times_ns[points.time_index])
    np.testing.assert_array_equal(np.concatenate(xyz), whole.xyz)
    np.testing.assert_array_equal(np.concatenate(times), base + whole.timestamp_ns)
    ranges = np.linalg.norm(whole.xyz, axis=1)
    assert 15 < np.median(ranges) < 30  # 4 mm range units: the reference cloud's median is 22.4 m


def test_the_mapper_decodes_a_hesai_s_published_packets_as_its_decoder_decodes_the_capture(tmp_path):
    payloads = capture("qt128", "hesai")
    config_path = vendor_config(tmp_path, "hesai-pandarqt128", "PandarQT128.csv")
    decoding = configured_decoding(load_config(config_path).sensors.lidar, config_path)
    stamps = decoding.new_decoder().check(payloads).sensor_time_ns
    packets = [LidarPacket(seq=i, sensor_time_ns=int(t), host_mono_ns=i, data=p)
               for i, (p, t) in enumerate(zip(payloads, stamps, strict=True))]
    scans = lidar_scans(packets, [], lambda: decoding, 1)
    assert 1 <= len(scans.scans) <= 3  # 0.2 s of a 10 Hz sensor
    whole = decoding.new_decoder().decode(payloads)
    np.testing.assert_array_equal(whole.packet_time_ns, stamps)  # the packets' own stamps, as check gives them
    decoded = [scans.decode(scan) for scan in scans.scans]
    np.testing.assert_array_equal(np.concatenate([d.xyz for d in decoded]), whole.xyz)
    np.testing.assert_array_equal(np.concatenate([d.times_ns[d.time_index] for d in decoded]), whole.timestamp_ns)


def test_check_config_refuses_a_calibration_of_another_model(tmp_path, capsys):
    config = vendor_config(tmp_path, "velodyne-vls128", "VLP16.yaml")
    assert check_config_main([str(config)]) == EXIT_CONFIG_ERROR
    err = capsys.readouterr().err
    assert "VLP16.yaml" in err and "16 lasers" in err and "128" in err, err
    good = vendor_config(tmp_path, "velodyne-vlp32c", "VLP32.yaml")
    data = yaml.safe_load(good.read_text())
    data["sensors"]["lidar"].pop("port")
    good.write_text(yaml.safe_dump(data))
    assert load_config(good).sensors.lidar.port == 2368  # Velodyne's factory port when none is given


def test_the_config_lists_exactly_the_vendor_models_that_decode():
    from daemon.spine.config import VENDOR_LIDARS as CONFIG_VENDOR_LIDARS

    assert set(CONFIG_VENDOR_LIDARS) == set(VENDOR_LIDARS)
