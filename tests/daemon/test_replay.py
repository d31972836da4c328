"""The log player: recorded segments go back into the bus as the drivers published them.

A drive published on the bus, recorded by the real recorder process and replayed by the real replay
process comes back unchanged (seq and host_mono_ns excepted); `--rate max` waits for a slow lossless
subscriber instead of overrunning it; `--rate 1.0` takes the recorded time; --start/--end cut the log;
topics the drivers do not publish are skipped and counted.
"""

from __future__ import annotations

import dataclasses
import json
import random
import signal
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
from daemon.log_format.reader import ReadReport, read_log
from daemon.log_format.writer import LogWriter
from daemon.processes.replay import replay, replayed_topics
from daemon.spine.config import load_config
from daemon.spine.messages import (
    CameraFrame,
    CanFrame,
    DriverHealth,
    ImuSample,
    LidarPacket,
    PointCloud,
    TimeAnchor,
    VehiclePose,
)
from daemon.spine.point_cloud_codec import pack_points
from daemon.spine.topics import (
    CAN_FRAMES,
    IMU,
    LIDAR_IMU,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    POSE,
    TIME_ANCHOR,
    camera_topic,
    health_topic,
)
from tests.daemon.test_log_damage import second_lz4_block_header
from tests.daemon_fixtures import private_config

ROOT = Path(__file__).resolve().parents[2]
DRIVE_TOPICS = (camera_topic("front_wide"), LIDAR_PACKETS, IMU, CAN_FRAMES)
STARTED: list[subprocess.Popen] = []  # killed at the end of each test, whatever happened


def start(*args: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", *args], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    STARTED.append(proc)
    return proc


def write_config(tmp_path: Path, extra_camera: bool = False, **bus_settings) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"] = {"shm_prefix": f"t{uuid.uuid4().hex[:12]}", **bus_settings}
    data["recorder"].update(min_free_gib=0.0, min_free_pct=0.0, segment_seconds=0.5)
    if extra_camera:
        data["sensors"]["cameras"].append(dict(data["sensors"]["cameras"][1], name="rear"))
    path = tmp_path / f"car_{uuid.uuid4().hex[:6]}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture
def configs():
    made = []

    def make(tmp_path, **kw):
        path = write_config(tmp_path, **kw)
        made.append(load_config(path))
        return path

    yield make
    while STARTED:
        proc = STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    for config in made:
        pubsub.unlink_all(config)


def without_bus_stamps(msg) -> object:
    return dataclasses.replace(msg, seq=0, host_mono_ns=0)


def run_replay(config_path: Path, logs: list[Path], *args: str) -> subprocess.Popen:
    return start("daemon.processes.replay", "--config", str(config_path), *args, *map(str, logs))


def collect(subs: dict[str, pubsub.Subscriber], expected: dict[str, int], proc: subprocess.Popen | None = None,
            timeout_s: float = 20.0, per_message_sleep_s: float = 0.0) -> dict[str, list]:
    """Read the subscribers until each has its expected count (copying payloads), within timeout_s."""
    got: dict[str, list] = {t: [] for t in subs}
    deadline = time.monotonic() + timeout_s
    while any(len(got[t]) < n for t, n in expected.items()) and time.monotonic() < deadline:
        idle = True
        for topic, sub in subs.items():
            msg = sub.read(timeout_s=0, copy=True)
            if msg is not None:
                idle = False
                got[topic].append((time.monotonic_ns(), msg))
                if per_message_sleep_s:
                    time.sleep(per_message_sleep_s)
        if idle:
            if proc is not None and proc.poll() is not None and all(s.backlog_bytes() == 0 for s in subs.values()):
                break
            time.sleep(0.001)
    return got


def test_a_recorded_drive_replays_unchanged(configs, tmp_path):
    config_path = configs(tmp_path)
    config = load_config(config_path)
    out = tmp_path / "logs"
    for t in DRIVE_TOPICS:
        pubsub.open_publisher(config, t).close()
    recorder = start("daemon.processes.recorder", "--config", str(config_path), "--output-dir", str(out))
    with pubsub.open_subscriber(config, health_topic("recorder"), wait_s=20) as health:
        assert health.read(timeout_s=20) is not None  # recording
        rng = random.Random(5)
        pubs = {t: pubsub.open_publisher(config, t) for t in DRIVE_TOPICS}
        sent: dict[str, list] = {t: [] for t in DRIVE_TOPICS}
        for i in range(80):
            batch = [(DRIVE_TOPICS[0], CameraFrame(sensor_time_ns=i * 100, camera="front_wide",
                                                   data=rng.randbytes(30_000))),
                     (LIDAR_PACKETS, LidarPacket(sensor_time_ns=i * 100 + 1, data=rng.randbytes(24_896))),
                     (IMU, ImuSample(sensor_time_ns=i * 100 + 2, accel_mps2=(rng.random(), 0.5, 9.8))),
                     (CAN_FRAMES, bus_can_frame(i))]
            for topic, msg in batch:
                pubs[topic].publish(msg)
                sent[topic].append(msg)
            time.sleep(0.02)
        while True:
            detail = json.loads(health.read(timeout_s=5).detail)
            if all(detail["written"].get(t, 0) == 80 for t in DRIVE_TOPICS):
                break
    recorder.send_signal(signal.SIGTERM)
    assert recorder.wait(timeout=20) == 0, recorder.stderr.read()
    for p in pubs.values():
        p.close()
    segments = sorted(out.glob("*.mcap"))
    assert len(segments) >= 2  # 0.5 s segments: the replay crosses segment boundaries

    subs = {t: pubsub.open_subscriber(config, t, lossless=True) for t in DRIVE_TOPICS}
    started_ns = time.monotonic_ns()
    proc = run_replay(config_path, segments, "--rate", "max")
    got = collect(subs, {t: 80 for t in DRIVE_TOPICS}, proc)
    assert proc.wait(timeout=20) == 0, proc.stderr.read()
    for topic in DRIVE_TOPICS:
        back = [m for _, m in got[topic]]
        assert [without_bus_stamps(m) for m in back] == [without_bus_stamps(m) for m in sent[topic]], topic
        assert [m.seq for m in back] == list(range(80, 160))  # the publisher continues the topic's sequence
        assert all(m.host_mono_ns > started_ns for m in back)  # on this host's clock, like a live driver
        # ... keeping the recorded arrival intervals, whatever the rate
        assert [b.host_mono_ns - back[0].host_mono_ns for b in back] == [
            m.host_mono_ns - sent[topic][0].host_mono_ns for m in sent[topic]]
        assert subs[topic].lost == 0
    with pubsub.open_subscriber(config, health_topic("replay"), start="latest") as replay_health:
        detail = json.loads(replay_health.read(timeout_s=1).detail)
    assert detail["fraction"] == 1.0 and detail["published"] == 4 * 80 + detail["published_per_topic"][TIME_ANCHOR]
    assert detail["published_per_topic"][TIME_ANCHOR] >= 1 and detail["skipped_per_topic"][health_topic("recorder")]


def test_stamps_on_the_recording_hosts_clock_move_with_the_host_times(configs, tmp_path):
    """A camera stamped on the host's monotonic clock (captured 35 ms before its arrival) keeps that latency
    after replay; a free-running IMU keeps its own stamps."""
    config_path = configs(tmp_path)
    config = load_config(config_path)
    cam = camera_topic("front_wide")
    t0 = 3_600_000_000_000  # the recording host's monotonic clock
    recorded = []
    for i in range(20):
        arrival = t0 + i * 100_000_000
        recorded.append((cam, CameraFrame(sensor_time_ns=arrival - 35_000_000, host_mono_ns=arrival,
                                          camera="front_wide", data=bytes(100))))
        recorded.append((IMU, ImuSample(sensor_time_ns=7_000 + i * 10_000, host_mono_ns=arrival + 1)))
    log = write_log(tmp_path / "drive.mcap", config_path, recorded)
    subs = {t: pubsub.open_subscriber(config, t, lossless=True, wait_s=0) for t in (cam, IMU)
            if pubsub.open_publisher(config, t).close() is None}
    proc = run_replay(config_path, [log], "--rate", "max")
    got = collect(subs, {cam: 20, IMU: 20}, proc)
    assert proc.wait(timeout=20) == 0, proc.stderr.read()
    frames, samples = [m for _, m in got[cam]], [m for _, m in got[IMU]]
    assert len(frames) == len(samples) == 20
    assert {f.host_mono_ns - f.sensor_time_ns for f in frames} == {35_000_000}  # the capture-to-arrival latency
    assert frames[0].host_mono_ns != t0  # on this host's clock now
    assert [s.sensor_time_ns for s in samples] == [7_000 + i * 10_000 for i in range(20)]


def bus_can_frame(i: int) -> CanFrame:
    return CanFrame(sensor_time_ns=i * 100 + 3, arbitration_id=0x100 + i % 7, channel="can0", data=bytes([i] * 8))


def write_log(path: Path, config_path: Path, messages: list[tuple[str, object]]) -> Path:
    with LogWriter(path, load_config(config_path)) as writer:
        for topic, msg in messages:
            writer.write(topic, msg)
    return path


def test_max_rate_waits_for_a_slow_lossless_subscriber(configs, tmp_path):
    config_path = configs(tmp_path, ring_bytes={LIDAR_PACKETS: 300_000})  # room for ~11 packets
    config = load_config(config_path)
    rng = random.Random(6)
    packets = [LidarPacket(i, 9_000_000_000 + i, 1_000_000 + 1_000 * i, "lidar", rng.randbytes(24_896))  # free-running
               for i in range(200)]
    log = write_log(tmp_path / "a.mcap", config_path, [(LIDAR_PACKETS, p) for p in packets])
    pubsub.open_publisher(config, LIDAR_PACKETS).close()
    slow = pubsub.open_subscriber(config, LIDAR_PACKETS, lossless=True)
    careless = pubsub.open_subscriber(config, LIDAR_PACKETS)  # a normal reader that falls behind
    proc = run_replay(config_path, [log], "--rate", "max")
    time.sleep(1.0)  # the replay fills the ring, then waits for the slow subscriber
    got = collect({LIDAR_PACKETS: slow}, {LIDAR_PACKETS: 200}, proc, per_message_sleep_s=0.002)
    assert proc.wait(timeout=20) == 0, proc.stderr.read()
    back = [m for _, m in got[LIDAR_PACKETS]]
    assert [without_bus_stamps(m) for m in back] == [without_bus_stamps(m) for m in packets]
    assert slow.lost == 0
    while careless.read(timeout_s=0) is not None:
        pass
    assert careless.lost > 0


def test_rate_one_takes_the_recorded_time(configs, tmp_path):
    config_path = configs(tmp_path)
    config = load_config(config_path)
    t0 = 10_000_000_000
    imu = [ImuSample(i, 7 + i, t0 + 10_000_000 * i, (0.0, 0.0, 9.8), (0.0, 0.0, 0.01)) for i in range(151)]
    log = write_log(tmp_path / "a.mcap", config_path, [(IMU, m) for m in imu])  # 1.5 s at 100 Hz
    pubsub.open_publisher(config, IMU).close()
    sub = pubsub.open_subscriber(config, IMU)
    proc = run_replay(config_path, [log], "--rate", "1.0")
    got = collect({IMU: sub}, {IMU: 151}, proc)[IMU]
    assert proc.wait(timeout=20) == 0, proc.stderr.read()
    assert len(got) == 151
    took = (got[-1][0] - got[0][0]) / 1e9
    assert 1.4 < took < 1.8, took
    stamped = (got[-1][1].host_mono_ns - got[0][1].host_mono_ns) / 1e9
    assert 1.45 < stamped < 1.6, stamped


def test_segments_merge_in_log_time_order_start_end_and_skipped_topics(configs, tmp_path):
    config_path = configs(tmp_path)
    config = load_config(config_path)
    bigger_car = configs(tmp_path, extra_camera=True)  # a log from a car with a fourth camera
    t0 = 50_000_000_000
    ms = 1_000_000
    imu = [ImuSample(i, i, t0 + 10 * ms * i) for i in range(200)]  # 2 s
    even = [(IMU, m) for m in imu[0::2]] + [(camera_topic("rear"), CameraFrame(0, 1, t0 + 5 * ms, "rear"))]
    odd = [(IMU, m) for m in imu[1::2]] + [
        (TIME_ANCHOR, TimeAnchor(0, t0, t0 + ms, 123)),
        (health_topic("lidar"), DriverHealth(0, t0, t0 + 2 * ms, "lidar")),
        (POSE, VehiclePose(sensor_time_ns=1, host_mono_ns=t0 + 3 * ms))]
    logs = [write_log(tmp_path / "b.mcap", bigger_car, even), write_log(tmp_path / "a.mcap", bigger_car, odd)]
    pubsub.open_publisher(config, IMU).close()
    sub = pubsub.open_subscriber(config, IMU, lossless=True)
    result = {}
    thread = threading.Thread(target=lambda: result.update(
        p=replay(config, logs, rate=None, start_s=0.5, end_s=1.0)))
    thread.start()
    got = collect({IMU: sub}, {IMU: 50})[IMU]
    thread.join(timeout=20)
    assert [m.sensor_time_ns for _, m in got] == list(range(50, 100))  # [0.5 s, 1.0 s) of the log, in order
    progress = result["p"]
    assert progress.published == {IMU: 50}
    full = replay(config, logs, rate=None)
    assert full.skipped == {camera_topic("rear"): 1, health_topic("lidar"): 1, POSE: 1}
    assert full.published == {IMU: 200, TIME_ANCHOR: 1} and full.fraction() == 1.0


def test_a_torn_unclosed_segment_replays_its_intact_chunks_once(configs, tmp_path):
    """replay on a segment left by a power cut with a torn block in its first chunk: the process plays every
    message of the intact chunks, once, reports the damage and exits 0 (it died on the lz4 error: a crash loop
    under the supervisor, which re-recorded the log several times over)."""
    config_path = configs(tmp_path)
    config = load_config(config_path)
    rng = random.Random(8)
    writer = LogWriter(tmp_path / "writing.mcap.open", config)
    for i in range(400):  # ~10 MB: two 4 MiB chunks reach the disk
        writer.write(LIDAR_PACKETS, LidarPacket(seq=i, sensor_time_ns=i * 100, host_mono_ns=10**9 + i * 10**6,
                                                data=rng.randbytes(24_896)))
        writer.write(IMU, ImuSample(seq=i, sensor_time_ns=i * 100 + 1, host_mono_ns=10**9 + i * 10**6 + 1,
                                    accel_mps2=(rng.random(), 0.0, 9.8)))
    writer.flush()  # the writer dies here: its written chunks, no footer
    torn = bytearray((tmp_path / "writing.mcap.open").read_bytes())
    block = second_lz4_block_header(bytes(torn)) // 4096 * 4096
    torn[block:block + 4096] = bytes(4096)
    segment = tmp_path / "torn.mcap.open"
    segment.write_bytes(torn)
    report = ReadReport()
    expected = {t: [r.message for r in read_log([segment], topics=[t], report=report)] for t in (LIDAR_PACKETS, IMU)}
    assert report.files[0].damaged_chunks == 1 and len(expected[LIDAR_PACKETS]) > 100
    seqs = [m.seq for m in expected[LIDAR_PACKETS]]
    assert seqs[0] > 0 and seqs == list(range(seqs[0], seqs[-1] + 1))  # the second chunk, whole

    for t in expected:
        pubsub.open_publisher(config, t).close()
    subs = {t: pubsub.open_subscriber(config, t, lossless=True) for t in expected}
    proc = run_replay(config_path, [segment], "--rate", "max")
    got = collect(subs, {t: len(m) for t, m in expected.items()}, proc)
    assert proc.wait(timeout=30) == 0, proc.stderr.read()
    for topic, msgs in expected.items():
        assert [without_bus_stamps(m) for _, m in got[topic]] == [without_bus_stamps(m) for m in msgs], topic
        assert subs[topic].read(timeout_s=0.2) is None  # once
    with pubsub.open_subscriber(config, health_topic("replay"), start="latest") as replay_health:
        detail = json.loads(replay_health.read(timeout_s=1).detail)
    assert detail["damaged_chunks"] == 1 and detail["incomplete_files"] == [str(segment)]
    assert detail["published"] == sum(len(m) for m in expected.values())


def test_replayed_topics_are_the_drivers_topics(configs, tmp_path):
    topics = replayed_topics(load_config(configs(tmp_path)))
    assert {camera_topic("front_wide"), "mask/front_left", LIDAR_PACKETS, IMU, "gnss/fix", CAN_FRAMES,
            "wheel_speeds"} <= topics
    assert not topics & {TIME_ANCHOR, POSE, health_topic("lidar"), health_topic("camera_front_wide")}


def test_a_point_cloud_lidars_scans_are_played_in_its_drivers_place(tmp_path):
    """A point-cloud Lidar has no live driver: the real player publishes its recorded clouds on lidar/points, whole
    (a 128-beam scan is ~2.6 MB), as a driver would; packets in a log of that car are not its topics: skipped."""
    config, config_path = private_config(tmp_path, point_clouds=True)
    rng = np.random.default_rng(4)
    clouds = [PointCloud(i, 1_700_000_000_000_000_000 + i * 100_000_000, 2_000_000_000 + i * 100_000_000, "lidar",
                         pack_points(rng.normal(0, 20, (131_072, 3)), rng.uniform(0, 255, 131_072),
                                     np.linspace(0, 0.1, 131_072))) for i in range(20)]
    log = write_log(tmp_path / "points.mcap", config_path, [(LIDAR_POINTS, c) for c in clouds])
    try:
        pubsub.open_publisher(config, LIDAR_POINTS).close()
        sub = pubsub.open_subscriber(config, LIDAR_POINTS, lossless=True)
        proc = start("daemon.processes.replay", "--config", str(config_path), "--rate", "max", str(log))
        got = collect({LIDAR_POINTS: sub}, {LIDAR_POINTS: 20}, proc, timeout_s=60)[LIDAR_POINTS]
        assert proc.wait(timeout=30) == 0, proc.stderr.read()
        assert [without_bus_stamps(m) for _, m in got] == [without_bus_stamps(c) for c in clouds]
        assert sub.lost == 0
        packets_car = write_config(tmp_path)
        packet_log = write_log(tmp_path / "packets.mcap", packets_car, [
            (LIDAR_PACKETS, LidarPacket(0, 5, 1_000, "lidar", b"x" * 100)), (LIDAR_IMU, ImuSample(0, 6, 1_001))])
        played = replay(config, [packet_log], rate=None)
        assert played.skipped == {LIDAR_PACKETS: 1, LIDAR_IMU: 1} and played.published == {}
    finally:
        while STARTED:
            started = STARTED.pop()
            if started.poll() is None:
                started.kill()
                started.wait()
        pubsub.unlink_all(config)
