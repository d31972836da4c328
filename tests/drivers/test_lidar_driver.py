"""The Lidar driver (drivers.lidar.udp_driver): Ouster packets through a real UDP socket on 127.0.0.1,
read back from the real bus written by the real process, or from the driver run in a thread."""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.bus import pubsub
from daemon.commands.check_config import main as check_config_main
from daemon.spine.config import EXIT_CONFIG_ERROR, load_config
from daemon.spine.health import HealthCounters
from daemon.spine.messages import DriverHealth, ImuSample, LidarPacket
from daemon.spine.topics import LIDAR_IMU, LIDAR_PACKETS, health_topic
from drivers.lidar import udp_driver
from drivers.lidar.ouster_encoder import encode_frame_packets
from drivers.lidar.ouster_metadata import metadata_to_json, parse_metadata, simulated_os128_metadata
from drivers.lidar.ouster_packet_layout import packet_layout, packets_per_second
from drivers.lidar.pcap_udp import read_pcap_udp

ROOT = Path(__file__).resolve().parents[2]
OUSTER = Path("/work/shared/data/ouster")
CAPTURES = {  # metadata JSON stem -> pcap stem
    "OS-0-128-U1_v2.3.0_1024x10": "OS-0-128-U1_v2.3.0_1024x10",  # RNG15_RFL8_NIR8
    "OS-0-32-U1_v2.2.0_1024x10": "OS-0-32-U1_v2.2.0_1024x10",  # RNG19_RFL8_SIG16_NIR16_DUAL
    "OS-1-128_767798045_1024x10_20230712_120049": "OS-1-128_767798045_1024x10_20230712_120049",  # FuSa
    "OS-1-128_v2.3.0_1024x10": "OS-1-128_v2.3.0_1024x10_lb_n3",  # 3 frames
    "OS-2-128-U1_v2.3.0_1024x10": "OS-2-128-U1_v2.3.0_1024x10",  # RNG19_RFL8_SIG16_NIR16
}
SERIAL = 122000000128
TIME_TOLERANCE_NS = 5_000_000  # kernel arrival time vs the sender's clock, on a loaded 2-core machine


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_config(tmp_path: Path, metadata_json: str, **lidar: object) -> Path:
    """sim.yaml with a unique bus prefix, a free lidar port and the metadata beside it."""
    (tmp_path / "lidar_metadata.json").write_text(metadata_json)
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"]["shm_prefix"] = f"t{uuid.uuid4().hex[:12]}"
    data["sensors"]["lidar"].update({"port": free_udp_port(), "metadata_file": "lidar_metadata.json", **lidar})
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def frame_packets(layout, frame_ids, t0_ns: int = 1_000_000_000) -> np.ndarray:
    """The packets of consecutive frames, random ranges, 100 us per column."""
    rng = np.random.default_rng(7)
    w, h = layout.columns_per_frame, layout.pixels_per_column
    out = []
    for f in frame_ids:
        times = t0_ns + (f * w + np.arange(w, dtype=np.uint64)) * 100_000
        pixels = {"range_mm": rng.integers(0, 200_000, (h, w)), "reflectivity": rng.integers(0, 255, (h, w))}
        out.append(encode_frame_packets(layout, f, pixels, times, init_id=7, prod_sn=SERIAL))
    return np.concatenate(out)


def send_paced(datagrams, port: int, rate_hz: float) -> np.ndarray:
    """Send each datagram at `rate_hz`; (N, 2) monotonic ns just before and after each send."""
    times = np.zeros((len(datagrams), 2), np.int64)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        start = time.monotonic()
        for i, d in enumerate(datagrams):
            delay = start + i / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            times[i, 0] = time.monotonic_ns()
            s.sendto(d, ("127.0.0.1", port))
            times[i, 1] = time.monotonic_ns()
    return times


def first_valid_times(packets: np.ndarray, layout) -> list[int]:
    """Timestamp of column 0 (all columns are valid in these packets)."""
    offset = layout.packet_header_size
    return [int.from_bytes(p[offset : offset + 8].tobytes(), "little") for p in packets]


class DriverProcess:
    """`python -m drivers.lidar.udp_driver` on a config, with its bus topics opened from the start."""

    def __init__(self, config_path: Path):
        self.car = load_config(config_path)
        self.proc = subprocess.Popen([sys.executable, "-m", "drivers.lidar.udp_driver", "--config", str(config_path)],
                                     cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.health = pubsub.open_subscriber(self.car, health_topic("lidar"), start="oldest", wait_s=20)
        first = self.health.read(timeout_s=20)  # sent once the socket listens
        assert first is not None, self.proc.stderr.read() if self.proc.poll() is not None else "no health"
        self.first_health = first
        self.packets = pubsub.open_subscriber(self.car, LIDAR_PACKETS, start="oldest", wait_s=5)

    def read_packets(self, n: int, timeout_s: float = 10) -> list[LidarPacket]:
        got: list[LidarPacket] = []
        deadline = time.monotonic() + timeout_s
        while len(got) < n and time.monotonic() < deadline:
            msg = self.packets.read(timeout_s=0.2, copy=True)
            if msg is not None:
                got.append(msg)
        return got

    def stop(self) -> tuple[str, DriverHealth]:
        self.proc.send_signal(signal.SIGTERM)
        out, err = self.proc.communicate(timeout=10)
        assert self.proc.returncode == 0, err
        last = None
        while (msg := self.health.read(timeout_s=0.3)) is not None:
            last = msg
        assert last is not None
        return out, last

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()
        self.health.close()
        if hasattr(self, "packets"):
            self.packets.close()
        pubsub.unlink_all(self.car)


@pytest.fixture
def driver_process():
    started: list[DriverProcess] = []

    def start(config_path: Path) -> DriverProcess:
        started.append(DriverProcess(config_path))
        return started[-1]

    yield start
    for d in started:
        d.close()


def test_process_publishes_every_packet_as_sent_with_arrival_and_sensor_times(tmp_path, driver_process):
    meta = simulated_os128_metadata(1024, udp_profile_lidar="RNG19_RFL8_SIG16_NIR16", prod_sn=str(SERIAL))
    layout = packet_layout(meta)
    driver = driver_process(write_config(tmp_path, metadata_to_json(meta)))
    assert driver.first_health.process == "lidar" and driver.first_health.received == 0
    packets = frame_packets(layout, range(100, 104))
    sent = send_paced([p.tobytes() for p in packets], driver.car.sensors.lidar.port, 5000)
    got = driver.read_packets(len(packets))
    assert len(got) == len(packets) == 256
    assert [m.data for m in got] == [p.tobytes() for p in packets]
    assert [m.sensor_time_ns for m in got] == first_valid_times(packets, layout)
    assert [m.seq for m in got] == list(range(got[0].seq, got[0].seq + len(got)))
    arrival = np.array([m.host_mono_ns for m in got])
    assert np.all(np.diff(arrival) >= 0)
    assert np.all(arrival >= sent[:, 0] - TIME_TOLERANCE_NS) and np.all(arrival <= sent[:, 1] + TIME_TOLERANCE_NS)
    out, health = driver.stop()
    assert "lidar driver stopped" in out and "packets=256" in out
    assert (health.received, health.published, health.dropped, health.sequence_gaps, health.rejected) == (
        256, 256, 0, 0, 0)
    assert "receive_buffer_bytes=" in health.detail


def test_process_counts_dropped_packets_and_rejects_garbage_without_publishing_it(tmp_path, driver_process):
    meta = simulated_os128_metadata(1024, udp_profile_lidar="RNG19_RFL8_SIG16_NIR16", prod_sn=str(SERIAL))
    layout = packet_layout(meta)
    driver = driver_process(write_config(tmp_path, metadata_to_json(meta)))
    packets = frame_packets(layout, [65534, 65535, 0, 1])  # the frame id wraps
    dropped = [3, 64, 65, 66, 130, 200]  # four gaps, six packets
    kept = [p.tobytes() for i, p in enumerate(packets) if i not in dropped]
    good = packets[10].copy()
    neighbour = good.copy()
    neighbour[7:12] = np.frombuffer((SERIAL + 1).to_bytes(5, "little"), np.uint8)  # another sensor's serial
    scrambled = good.copy()
    scrambled[layout.packet_header_size + layout.column_size + 8] ^= 0x55  # measurement id of column 1
    garbage = [b"", b"\x01" * 48, good[:1000].tobytes(), good[:-1].tobytes(), good.tobytes() + b"\0",
               bytes(60000), neighbour.tobytes(), scrambled.tobytes()]
    stream = kept[:100] + garbage[:4] + kept[100:180] + garbage[4:] + kept[180:]  # the driver goes on after each
    send_paced(stream, driver.car.sensors.lidar.port, 5000)
    got = driver.read_packets(len(kept))
    assert [m.data for m in got] == kept
    assert driver.read_packets(1, timeout_s=0.5) == []  # nothing else: no garbage on the bus
    out, health = driver.stop()
    assert (health.received, health.published, health.rejected) == (len(stream), len(kept), len(garbage))
    assert (health.dropped, health.sequence_gaps) == (len(dropped), 4)
    assert "wrong_size=6 bad_header=2" in health.detail and "missing_packets=6 gaps=4 restarts=0" in out


@pytest.mark.parametrize("stem", sorted(CAPTURES))
def test_real_ouster_captures_through_the_socket_decode_without_rejects(stem, tmp_path):
    meta = parse_metadata(OUSTER / f"{stem}.json")
    payloads = [d.payload for d in read_pcap_udp(OUSTER / f"{CAPTURES[stem]}.pcap", meta.udp_port_lidar).datagrams]
    config = load_config(write_config(tmp_path, (OUSTER / f"{stem}.json").read_text())).sensors.lidar
    result = run_in_thread(config, meta, lambda: send_paced(payloads, config.port, 5000), len(payloads))
    assert [m.data for m in result.packets] == payloads
    assert result.stats.wrong_size == result.stats.bad_header == result.health.rejected == 0
    assert result.health.dropped == result.stats.missing_packets == 0
    layout = packet_layout(meta)
    sensor_times = [m.sensor_time_ns for m in result.packets]
    sent = np.frombuffer(b"".join(payloads), np.uint8).reshape(-1, layout.packet_size)
    assert sensor_times == first_valid_times(sent, layout)


def test_the_lidar_imu_of_a_real_capture_is_published_as_the_ouster_sdk_reads_it(tmp_path):
    """The OS-1-128 capture's Lidar and IMU datagrams, in capture order, each to its own UDP port of the
    driver process; garbage IMU datagrams between them are counted and skipped."""
    import ouster.sdk.core as ouster

    stem = "OS-1-128_v2.3.0_1024x10"
    meta = parse_metadata(OUSTER / f"{stem}.json")
    capture = read_pcap_udp(OUSTER / f"{CAPTURES[stem]}.pcap").datagrams
    imu_port = free_udp_port()
    driver = DriverProcess(write_config(tmp_path, (OUSTER / f"{stem}.json").read_text(), imu_port=imu_port))
    try:
        imu_sub = pubsub.open_subscriber(driver.car, LIDAR_IMU, start="oldest", wait_s=5)
        ports = {meta.udp_port_lidar: driver.car.sensors.lidar.port, meta.udp_port_imu: imu_port}
        imu_sent = [d.payload for d in capture if d.dst_port == meta.udp_port_imu]
        garbage = [b"\x01" * 40, imu_sent[0][:24] + struct.pack("<6f", float("nan"), 0, 0, 0, 0, 0)]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for i, d in enumerate(capture):
                if d.dst_port in ports:
                    s.sendto(d.payload, ("127.0.0.1", ports[d.dst_port]))
                if i == 100:
                    for g in garbage:
                        s.sendto(g, ("127.0.0.1", imu_port))
                time.sleep(0.0002)
        got = []
        deadline = time.monotonic() + 10
        while len(got) < len(imu_sent) and time.monotonic() < deadline:
            if (msg := imu_sub.read(timeout_s=0.2)) is not None:
                got.append(msg)
        out, health = driver.stop()
    finally:
        driver.close()
    assert len(imu_sent) == 30 and len(got) == 30
    fmt, g = ouster.PacketFormat(ouster.SensorInfo((OUSTER / f"{stem}.json").read_text())), 9.80665
    for sample, payload in zip(got, imu_sent, strict=True):
        buf = np.frombuffer(payload, np.uint8)
        assert sample.sensor_time_ns == fmt.imu_accel_ts(buf)
        assert np.allclose(sample.accel_mps2, [g * fmt.imu_la_x(buf), g * fmt.imu_la_y(buf), g * fmt.imu_la_z(buf)])
        assert np.allclose(sample.gyro_rps, np.radians([fmt.imu_av_x(buf), fmt.imu_av_y(buf), fmt.imu_av_z(buf)]))
    assert 9.0 < np.linalg.norm(got[0].accel_mps2) < 11.0  # a sensor at rest reads gravity
    assert f"imu=listening on {imu_port} imu_samples=30 imu_rejected=2" in out
    assert health.rejected == 2 and health.published > 0


def test_an_imu_profile_without_a_decoder_or_a_taken_port_leaves_the_lidar_running(tmp_path):
    config = load_config(write_config(tmp_path, metadata_to_json(simulated_os128_metadata(512)))).sensors.lidar
    newer = parse_metadata(OUSTER / "imu_zm_no_lidar_0.json")  # firmware 3.1: ACCEL32_GYRO32_NMEA
    stats, health = udp_driver.LidarDriverStats(), HealthCounters("lidar")
    assert udp_driver._open_imu_socket(config, newer, stats, health) is None
    assert stats.imu == "not decoded: IMU profile ACCEL32_GYRO32_NMEA" and "has no decoder" in health.last_error
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("0.0.0.0", 0))
        busy = config.model_copy(update={"imu_port": taken.getsockname()[1]})
        stats, health = udp_driver.LidarDriverStats(), HealthCounters("lidar")
        assert udp_driver._open_imu_socket(busy, simulated_os128_metadata(512), stats, health) is None
        assert stats.imu.startswith("not listening") and health.errors == 1
    off = config.model_copy(update={"imu_port": 0})
    assert udp_driver._open_imu_socket(off, simulated_os128_metadata(512), stats, health) is None


def test_a_restarted_sensor_is_counted_anew(tmp_path):
    meta = simulated_os128_metadata(512)
    layout = packet_layout(meta)
    config = load_config(write_config(tmp_path, metadata_to_json(meta))).sensors.lidar
    before = frame_packets(layout, [700, 701])
    after = np.delete(frame_packets(layout, [0, 1]), [5, 40], axis=0)  # restarted at frame 0, two lost
    stream = [p.tobytes() for p in np.concatenate([before, after])]

    def send() -> None:
        send_paced(stream[: len(before)], config.port, 5000)
        time.sleep(0.1)  # a batch of its own for each side of the restart
        send_paced(stream[len(before) :], config.port, 5000)

    result = run_in_thread(config, meta, send, len(stream))
    assert len(result.packets) == len(stream)
    assert (result.stats.restarts, result.stats.missing_packets, result.stats.gaps) == (1, 2, 2)
    assert "sensor restarted" in result.health.last_error and result.health.errors == 1


def test_a_small_receive_buffer_shortens_the_batches_and_loses_nothing_at_the_sensor_rate(tmp_path):
    meta = simulated_os128_metadata(2048)  # 1,280 packets/s of 24,896 B
    layout = packet_layout(meta)
    config = load_config(write_config(tmp_path, metadata_to_json(meta), receive_buffer_bytes=1 << 20)).sensors.lidar
    stream = [p.tobytes() for p in frame_packets(layout, range(10))]
    result = run_in_thread(config, meta, lambda: send_paced(stream, config.port, 1280), len(stream))
    granted = result.stats.receive_buffer_bytes
    assert result.stats.batch_period_ms < 20 and result.stats.batch_period_ms == pytest.approx(
        1000 * granted / (2 * layout.packet_size) / 1280 / 4, rel=1e-3)
    assert len(result.packets) == len(stream) and result.stats.missing_packets == result.stats.kernel_drops == 0


def test_a_lidar_model_without_a_decoder_is_a_config_error(tmp_path, capsys):
    """The config accepts exactly the models that decode: another one is refused when the config is read, so
    check-config refuses it too and the driver exits 2 (not retried) instead of dying later."""
    meta_json = metadata_to_json(simulated_os128_metadata(1024))
    for model in ("hesai-pandar128", "velodyne-hdl32e"):
        path = write_config(tmp_path, meta_json, model=model)
        assert udp_driver.main(["--config", str(path)]) == EXIT_CONFIG_ERROR
        err = capsys.readouterr().err
        assert "sensors.lidar.model" in err and "ouster-os-128" in err and "Traceback" not in err
        assert check_config_main([str(path)]) == EXIT_CONFIG_ERROR
        assert "sensors.lidar.model" in capsys.readouterr().err


def test_the_ouster_driver_refuses_a_point_cloud_lidar(tmp_path, capsys):
    """A point-cloud Lidar's scans come decoded, only in logs: the packet driver started on it exits 2 (not retried),
    naming the model, instead of failing on the metadata file it has not got."""
    path = write_config(tmp_path, "{}", model="point-cloud", metadata_file=None)
    assert udp_driver.main(["--config", str(path)]) == EXIT_CONFIG_ERROR
    err = capsys.readouterr().err
    assert "sensors.lidar.model 'point-cloud' has no Ouster metadata_file" in err and "Traceback" not in err


def test_unusable_metadata_and_a_taken_port_are_clear_errors(tmp_path, capsys):
    path = write_config(tmp_path, "{}")
    assert udp_driver.main(["--config", str(path)]) == EXIT_CONFIG_ERROR
    assert "sensors.lidar.metadata_file" in capsys.readouterr().err
    path = write_config(tmp_path, metadata_to_json(simulated_os128_metadata(1024)))
    car = load_config(path)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", car.sensors.lidar.port))
        try:
            assert udp_driver.main(["--config", str(path)]) == 1
        finally:
            pubsub.unlink_all(car)
    assert f"cannot listen for lidar packets on UDP 127.0.0.1:{car.sensors.lidar.port}" in capsys.readouterr().err


class DriverRun:
    def __init__(self) -> None:
        self.packets: list[LidarPacket] = []
        self.imu: list[ImuSample] = []
        self.healths: list[DriverHealth] = []
        self.listening = threading.Event()
        self.stats: udp_driver.LidarDriverStats | None = None
        self.health: HealthCounters | None = None

    def publish(self, topic: str, message: object) -> None:
        if topic == LIDAR_PACKETS:
            self.packets.append(message)
        elif topic == LIDAR_IMU:
            self.imu.append(message)
        else:
            self.healths.append(message)
            self.listening.set()


def run_in_thread(config, meta, send, n_expected: int, timeout_s: float = 10) -> DriverRun:
    """run_lidar_driver in a thread until `send` has sent and n_expected packets came out."""
    run = DriverRun()
    run.health = HealthCounters("lidar", expected_rate_hz=packets_per_second(meta))
    stop = threading.Event()

    def target() -> None:
        run.stats = udp_driver.run_lidar_driver(config, meta, run.publish, stop, run.health)

    thread = threading.Thread(target=target)
    thread.start()
    try:
        assert run.listening.wait(10)
        send()
        deadline = time.monotonic() + timeout_s
        while len(run.packets) < n_expected and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        stop.set()
        thread.join(10)
    return run


@pytest.mark.slow
def test_process_keeps_up_with_an_os128_2048x10_without_loss(tmp_path, driver_process):
    """The sensor's real rate (1,280 packets/s of 24,896 B) for 5 s: prints the driver's CPU use."""
    meta = simulated_os128_metadata(2048)
    layout = packet_layout(meta)
    driver = driver_process(write_config(tmp_path, metadata_to_json(meta), columns_per_frame=2048))
    frames = frame_packets(layout, range(50))
    got: list[LidarPacket] = []
    reader = threading.Thread(target=lambda: got.extend(driver.read_packets(len(frames), timeout_s=20)))
    reader.start()  # read as the recorder does, while the packets come: the ring holds ~5 s of them
    cpu = _process_cpu_s(driver.proc.pid)
    wall = time.monotonic()
    send_paced([p.tobytes() for p in frames], driver.car.sensors.lidar.port, 1280)
    reader.join()
    wall = time.monotonic() - wall
    cpu = _process_cpu_s(driver.proc.pid) - cpu
    _, health = driver.stop()
    print(f"\n{len(frames)} packets at 1280/s: received {len(got)}, dropped {health.dropped}, "
          f"driver CPU {cpu:.2f} s in {wall:.2f} s ({100 * cpu / wall:.1f} %)")
    assert len(got) == len(frames) and driver.packets.lost == 0
    assert health.published == len(frames) and health.dropped == 0 and health.rejected == 0


def _process_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
