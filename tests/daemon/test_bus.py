"""The message bus between real processes: size classes, overtaking, kills, lossless publishing, timeouts."""

from __future__ import annotations

import multiprocessing
import os
import signal
import statistics
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from daemon.bus.pubsub import open_publisher, open_subscriber, ring_path, unlink_all, unlink_topic
from daemon.spine.config import load_config
from daemon.spine.messages import CameraFrame, ImuSample, LidarPacket
from daemon.spine.topics import LIDAR_PACKETS, camera_topic

SPAWN = multiprocessing.get_context("spawn")
SIM_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "sim.yaml"
CAMERA = camera_topic("front_wide")
SIZE_CLASSES = (0, 1024, 64 * 1024, 1 << 20, 3840 * 2160 * 3)


def make_config(ring_bytes: dict[str, int] | None = None):
    base = load_config(SIM_CONFIG)
    bus = base.bus.model_copy(update={"shm_prefix": f"rltest_{uuid.uuid4().hex[:10]}",
                                      "ring_bytes": ring_bytes or {}})
    return base.model_copy(update={"bus": bus})


@pytest.fixture
def config():
    cfg = make_config({LIDAR_PACKETS: 256 * 1024})
    yield cfg
    unlink_all(cfg)


def payload(seq: int, n: int) -> np.ndarray:
    """Bytes derived from the sequence number: (7 * i + 13 * seq) mod 256."""
    return (np.arange(n, dtype=np.uint32) * 7 + 13 * seq).astype(np.uint8)


def intact(message) -> bool:
    return np.array_equal(np.frombuffer(message.data, np.uint8), payload(message.seq, len(message.data)))


def _subscribe(config, topic: str, count: int, delay_s: float, lossless: bool, copy: bool, ready, results
               ) -> None:
    """Read up to seq count - 1 (or until 10 s of silence); report what arrived and whether it was intact."""
    sub = open_subscriber(config, topic, start="oldest", lossless=lossless, wait_s=10)
    ready.put(os.getpid())
    bad, seqs, sizes, latencies_ns = 0, [], set(), []
    while (message := sub.read(10, copy=copy)) is not None:
        latencies_ns.append(time.monotonic_ns() - message.host_mono_ns)
        ok = intact(message) and (topic != CAMERA or message.camera == "front_wide")
        if not ok and (copy or sub.still_valid()):  # a zero-copy view may only change once invalid
            bad += 1
        seqs.append(message.seq)
        sizes.add(len(message.data))
        if message.seq >= count - 1:
            break
        time.sleep(delay_s)
    results.put({"pid": os.getpid(), "received": sub.received, "lost": sub.lost, "bad": bad, "seqs": seqs,
                 "sizes": sorted(sizes), "latency_ms_median": statistics.median(latencies_ns) / 1e6
                 if latencies_ns else None})


def _start_subscribers(config, topic, count, specs, results):
    """specs: (delay_s, lossless, copy) per subscriber process; returns once all have subscribed."""
    ready = SPAWN.Queue()
    procs = [SPAWN.Process(target=_subscribe, args=(config, topic, count, *spec, ready, results))
             for spec in specs]
    for p in procs:
        p.start()
    for _ in procs:
        ready.get(timeout=30)
    return procs


def test_every_size_class_reaches_two_lossless_subscriber_processes_intact(config):
    pub = open_publisher(config, CAMERA)
    results = SPAWN.Queue()
    count = 2 * len(SIZE_CLASSES)
    procs = _start_subscribers(config, CAMERA, count, [(0, True, False), (0.01, True, True)], results)
    for i in range(count):
        n = SIZE_CLASSES[i % len(SIZE_CLASSES)]
        seq = pub.next_seq
        frame = CameraFrame(camera="front_wide", format="rgb8", width=n and 3840, height=n and 2160,
                            data=payload(seq, n))
        assert pub.publish(frame, lossless=True, timeout_s=20) == seq == frame.seq
        assert frame.host_mono_ns > 0
    outcomes = [results.get(timeout=60) for _ in procs]
    for p in procs:
        p.join(10)
    for out in outcomes:
        assert (out["received"], out["lost"], out["bad"]) == (count, 0, 0)
        assert out["seqs"] == list(range(count))
        assert out["sizes"] == sorted(SIZE_CLASSES)


def test_slow_subscriber_is_overtaken_and_counts_exactly(config):
    results = SPAWN.Queue()
    count = 600
    pub = open_publisher(config, LIDAR_PACKETS)  # a 256 KB ring: about 100 of these messages
    procs = _start_subscribers(config, LIDAR_PACKETS, count, [(0.005, False, True), (0, False, False)], results)
    for seq in range(count):
        pub.publish(LidarPacket(data=payload(seq, 1000 + seq % 3000)))
    outcomes = [results.get(timeout=60) for _ in procs]
    for p in procs:
        p.join(10)
    slow, fast = sorted(outcomes, key=lambda o: -o["lost"])
    assert slow["lost"] > 0 and slow["bad"] == 0 and fast["bad"] == 0
    for out in outcomes:
        assert out["received"] + out["lost"] == count
        assert out["seqs"][-1] == count - 1
        assert out["seqs"] == sorted(out["seqs"])


def test_lossless_publish_waits_for_a_slow_registered_subscriber(config):
    results = SPAWN.Queue()
    count = 400
    pub = open_publisher(config, LIDAR_PACKETS)  # a 256 KB ring: about 60 of these messages
    procs = _start_subscribers(config, LIDAR_PACKETS, count, [(0.001, True, False)], results)
    for seq in range(count):
        pub.publish(LidarPacket(data=payload(seq, 4000)), lossless=True, timeout_s=10)
    out = results.get(timeout=60)
    procs[0].join(10)
    assert (out["received"], out["lost"], out["bad"]) == (count, 0, 0)


def test_killed_lossless_subscriber_does_not_block_the_publisher(config):
    results = SPAWN.Queue()
    count = 300
    pub = open_publisher(config, LIDAR_PACKETS)
    stuck, fine = _start_subscribers(config, LIDAR_PACKETS, count, [(10, True, False), (0, True, False)],
                                     results)
    for seq in range(20):
        pub.publish(LidarPacket(data=payload(seq, 4000)), lossless=True, timeout_s=10)
    with pytest.raises(TimeoutError):  # the stuck subscriber holds the writer back ...
        while pub.next_seq < count:
            pub.publish(LidarPacket(data=payload(pub.next_seq, 4000)), lossless=True, timeout_s=0.2)
    os.kill(stuck.pid, signal.SIGKILL)  # ... until it dies
    while pub.next_seq < count:
        pub.publish(LidarPacket(data=payload(pub.next_seq, 4000)), lossless=True, timeout_s=2)
    out = results.get(timeout=60)
    fine.join(10)
    stuck.join(10)
    assert (out["received"], out["lost"], out["bad"]) == (count, 0, 0)


def _publish_forever(config, topic: str, size: int) -> None:
    pub = open_publisher(config, topic)
    while True:
        pub.publish(LidarPacket(data=payload(pub.next_seq, size)))
        time.sleep(0.0005)


def test_publisher_killed_and_restarted_resumes_the_sequence(config):
    first = SPAWN.Process(target=_publish_forever, args=(config, LIDAR_PACKETS, 2000))
    first.start()
    sub = open_subscriber(config, LIDAR_PACKETS, start="oldest", wait_s=20)
    seqs = []
    while len(seqs) < 100:
        message = sub.read(10, copy=True)
        assert intact(message)
        seqs.append(message.seq)
    os.kill(first.pid, signal.SIGKILL)
    first.join(10)
    second = SPAWN.Process(target=_publish_forever, args=(config, LIDAR_PACKETS, 2000))
    second.start()
    while seqs[-1] < 250:  # the subscriber waits through the restart
        message = sub.read(20, copy=True)
        assert message is not None and intact(message)
        seqs.append(message.seq)
    os.kill(second.pid, signal.SIGKILL)
    second.join(10)
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert sub.received + sub.lost == seqs[-1] + 1


def test_read_timeout_and_waiting_for_the_ring(config):
    t0 = time.monotonic()
    with pytest.raises(FileNotFoundError, match="imu"):
        open_subscriber(config, "imu", wait_s=0.2)
    assert time.monotonic() - t0 >= 0.2
    threading.Timer(0.2, lambda: open_publisher(config, "imu").publish(ImuSample())).start()
    sub = open_subscriber(config, "imu", start="oldest", wait_s=5)
    assert sub.read(5).seq == 0
    t0 = time.monotonic()
    assert sub.read(0.15) is None
    assert 0.14 <= time.monotonic() - t0 < 1.0


def _latency_probe(config, results) -> None:
    sub = open_subscriber(config, "imu", wait_s=10)
    results.put("ready")
    latencies = []
    while len(latencies) < 200:
        message = sub.read(5)
        assert message is not None
        latencies.append(time.monotonic_ns() - message.host_mono_ns)
    results.put(statistics.median(latencies) / 1e6)


def test_waiting_subscriber_wakes_well_under_a_millisecond(config):
    pub = open_publisher(config, "imu")
    results = SPAWN.Queue()
    probe = SPAWN.Process(target=_latency_probe, args=(config, results))
    probe.start()
    assert results.get(timeout=30) == "ready"
    time.sleep(0.05)
    for _ in range(200):
        pub.publish(ImuSample(accel_mps2=(0.0, 0.0, 9.81)))
        time.sleep(0.002)
    median_ms = results.get(timeout=30)
    probe.join(10)
    assert median_ms < 1.0


def test_too_large_and_wrong_type_messages_are_refused(config):
    pub = open_publisher(config, LIDAR_PACKETS)
    with pytest.raises(ValueError, match=r"lidar/packets.*300000 B payload.*262144 B ring"):
        pub.publish(LidarPacket(data=bytes(300_000)))
    with pytest.raises(TypeError, match="LidarPacket"):
        pub.publish(ImuSample())
    with pytest.raises(KeyError, match="no/such"):
        open_publisher(config, "no/such")


def test_zero_copy_data_is_read_only_and_revalidated(config):
    pub = open_publisher(config, LIDAR_PACKETS)
    sub = open_subscriber(config, LIDAR_PACKETS)
    pub.publish(LidarPacket(sensor_time_ns=5, data=payload(0, 100_000)))
    message = sub.read(1)
    assert message.sensor_time_ns == 5 and isinstance(message.data, memoryview) and message.data.readonly
    assert sub.still_valid()
    for _ in range(3):
        pub.publish(LidarPacket(data=payload(1, 100_000)))
    assert not sub.still_valid()
    assert sub.latest().seq == 3 and sub.skipped == 2 and sub.lost == 0
    assert bytes(sub.latest().data) == payload(1, 100_000).tobytes()  # the newest again
    assert sub.read(0) is None


def test_unlinked_topic_is_followed_to_its_new_ring(config):
    pub = open_publisher(config, "imu")
    sub = open_subscriber(config, "imu")
    pub.publish(ImuSample())
    assert sub.read(1).seq == 0
    pub.close()
    unlink_topic(config, "imu")
    assert not os.path.exists(ring_path(config, "imu"))
    threading.Timer(0.2, lambda: open_publisher(config, "imu").publish(ImuSample(sensor_time_ns=7))).start()
    message = sub.read(5)
    assert (message.seq, message.sensor_time_ns, sub.lost) == (0, 7, 0)
