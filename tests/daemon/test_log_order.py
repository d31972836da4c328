"""Messages in log-time order within each chunk: the reorder buffer on its own, and a segment the real recorder wrote
from rings it read out of order (a backlog at start, stale stamps), checked by the mcap Python library's stream reader
and by an independent reader, the TypeScript @mcap/core (node, from npm into tests/.node/; skipped with the reason
when it cannot be installed)."""

from __future__ import annotations

import json
import os
import random
import subprocess
import time
from pathlib import Path

import pytest
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from daemon.bus import pubsub
from daemon.log_format.metadata_records import LOG_TIME_OFFSET_KEY
from daemon.log_format.reader import read_log, read_metadata
from daemon.processes.reorder_buffer import ReorderBuffer
from daemon.spine.config import load_config
from daemon.spine.messages import CameraFrame, ImuSample, LidarPacket, VehiclePose
from daemon.spine.topics import IMU, LIDAR_PACKETS, POSE_STAMP_LAG_S, VEHICLE_POSE, camera_topic
from tests.daemon.test_recorder import RecorderProcess, write_config
from tests.node_packages import node_modules

CHUNK_ORDER_JS = Path(__file__).with_name("mcap_chunk_order.js")
CAMERA = camera_topic("front_wide")
S = 1_000_000_000


def at(t_s: float, topic: str = "imu") -> tuple[str, ImuSample]:
    return topic, ImuSample(host_mono_ns=int(t_s * S))


def test_the_buffer_releases_oldest_first_what_no_ring_can_precede():
    buf = ReorderBuffer(window_ns=5 * S, max_bytes=10**9)
    for topic, msg in (at(10.0), at(9.0, "lidar"), at(12.0), at(9.5, "lidar")):
        assert buf.push(topic, msg)
    assert [m.host_mono_ns for _, m in buf.pop_ready(safe_ns=9.6 * S)] == [9 * S, 9.5 * S]
    assert list(buf.pop_ready(safe_ns=None)) == []  # 12 s is the newest: 10 s is within the window
    assert buf.push(*at(15.5))  # now 10 s is more than the window older than the newest
    assert [m.host_mono_ns for _, m in buf.pop_ready()] == [10 * S]
    assert not buf.push(*at(9.9, "lidar"))  # older than what was released: late, written at once
    assert buf.late == {"lidar": 1} and len(buf) == 2
    assert [m.host_mono_ns for _, m in buf.drain()] == [12 * S, 15.5 * S] and buf.bytes_held == 0


def test_the_buffer_never_holds_more_than_its_bytes():
    buf = ReorderBuffer(window_ns=60 * S, max_bytes=3000)
    for k in range(5):
        buf.push(LIDAR_PACKETS, LidarPacket(host_mono_ns=k, data=bytes(1000)))
    released = list(buf.pop_ready())
    assert [m.host_mono_ns for _, m in released] == [0, 1, 2] and buf.bytes_held == 2 * (1000 + 64)


def test_a_replay_holds_a_played_ring_read_ahead_until_the_ring_behind_it_is_read(tmp_path):
    """`replay --rate max` publishes 0.3 s of log time in milliseconds, so in one round of reads one played ring can
    be read a window ahead of another that is still to give older messages. The played rings' bounds are exact (the
    player publishes in log-time order): nothing is released past them, and the ring behind is not late. Live, the
    window still releases what waits on a ring the recorder fell behind on (counted late when that ring comes)."""
    from daemon.processes.recorder import Recorder
    from daemon.spine.messages import CanFrame
    from daemon.spine.topics import CAN_FRAMES

    def can(t_s: float) -> CanFrame:
        return CanFrame(host_mono_ns=int(t_s * S), arbitration_id=0x200, data=bytes(8))

    config = load_config(write_config(tmp_path, reorder_window_s=0.3))
    for live in (False, True):
        rec = Recorder(config, tmp_path / f"logs_{live}", live=live)
        for t in (0.10, 0.20):  # the CAN ring, read to its end
            rec.accept(CAN_FRAMES, can(t))
        for t in (0.15, 0.45, 0.75, 1.05):  # the IMU ring, read after the player went on
            rec.accept(IMU, at(t)[1])
        rec.release(safe_ns=int(0.20 * S))  # the CAN ring's bound: its last message read
        rec.accept(CAN_FRAMES, can(0.50))  # the CAN ring's next read
        assert rec.late() == ({CAN_FRAMES: 1} if live else {}), live
        rec.release_everything()
        rec.close_segment()


def chunks_in_file_order(path: Path) -> list[tuple[Chunk, list[int]]]:
    """Each chunk record as the file holds it, with its messages' log times in the order they are stored (the mcap
    library's stream reader, not ours)."""
    out = []
    with open(path, "rb") as f:
        for record in StreamReader(f, emit_chunks=True, validate_crcs=True).records:
            if isinstance(record, Chunk):
                out.append((record, [m.log_time for m in breakup_chunk(record, validate_crc=True)
                                     if isinstance(m, Message)]))
    return out


def publish_out_of_order_drive(config, recorder_start):
    """A backlog of 2.5 s in three rings before the recorder starts (it reads them in turns, READ_BURST at a time,
    so their messages reach it seconds apart), 1.5 s more once it runs, and in its last half second three IMU
    samples stamped 8 s before they are published (older than what it wrote by then: late). Returns what was
    published per topic and the recorder."""
    rng = random.Random(5)
    pubs = {t: pubsub.open_publisher(config, t) for t in (CAMERA, LIDAR_PACKETS, IMU)}
    sent = {t: [] for t in pubs}

    def publish(topic, msg):
        pubs[topic].publish(msg)
        sent[topic].append(msg)

    rec = None
    t0 = time.monotonic()
    k = stale = 0
    end = t0 + 60
    while time.monotonic() < end or (rec is not None and stale < 3):  # all three stale ones, however slow the loop
        if rec is None and time.monotonic() - t0 >= 2.5:
            rec = recorder_start()
            end = time.monotonic() + 1.5
        for _ in range(4):
            publish(LIDAR_PACKETS, LidarPacket(sensor_time_ns=k, data=rng.randbytes(3000)))
        publish(IMU, ImuSample(sensor_time_ns=k, accel_mps2=(rng.random(), 0.0, 9.81)))
        if k % 4 == 0:
            publish(CAMERA, CameraFrame(sensor_time_ns=k, camera="front_wide", format="jpeg",
                                        data=rng.randbytes(5000)))
        if rec is not None and end - time.monotonic() < 0.5 and k % 20 == 0 and stale < 3:
            if stale == 0:  # late is older than what was written: under load the recorder may not have written yet
                rec.wait_for(lambda d: sum(d["written"].values()) > 0)
            publish(IMU, ImuSample(sensor_time_ns=k, host_mono_ns=time.monotonic_ns() - 8 * S))
            stale += 1
        k += 1
        time.sleep(0.005)
    for p in pubs.values():
        p.close()
    return sent, rec


@pytest.fixture(scope="module")
def node_mcap() -> Path:
    """tests/.node/node_modules with @mcap/core and lz4js."""
    return node_modules("@mcap/core@2", "lz4js@0.2")


def typescript_chunks(node_modules: Path, path: Path) -> dict:
    done = subprocess.run(["node", str(CHUNK_ORDER_JS), str(path)], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, NODE_PATH=str(node_modules)), check=True)
    return json.loads(done.stdout)


@pytest.fixture(scope="module")
def recorded_segment(tmp_path_factory):
    """One segment the real recorder wrote from an out-of-order drive, with what was sent and its health."""
    tmp_path = tmp_path_factory.mktemp("order")
    config_path = write_config(tmp_path)
    config = load_config(config_path)
    out = tmp_path / "logs"
    wall_before = time.time_ns()
    try:
        sent, rec = publish_out_of_order_drive(config, lambda: RecorderProcess(config_path, out))
        detail = rec.wait_written({t: len(m) for t, m in sent.items()})
        assert rec.stop() == 0, rec.stderr
    finally:
        while RecorderProcess.started:
            proc = RecorderProcess.started.pop()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        pubsub.unlink_all(config)
    [segment] = sorted(out.glob("*.mcap"))
    return segment, sent, detail, (wall_before, time.time_ns())


def test_a_recorded_segment_has_every_chunk_in_log_time_order(recorded_segment):
    segment, sent, detail, (wall_before, wall_after) = recorded_segment
    back = {}
    for rec in read_log([segment]):
        back.setdefault(rec.topic, []).append(rec.message)
    for topic, msgs in sent.items():  # nothing dropped, late ones included
        assert sorted(back[topic], key=lambda m: m.seq) == msgs, topic
    assert detail["late"] == {IMU: 3}
    counts = read_metadata(segment)["roadlog.counts"]
    assert json.loads(counts["late_per_topic"]) == {IMU: 3}
    chunks = chunks_in_file_order(segment)
    assert len(chunks) >= 3
    for chunk, times in chunks:
        assert times == sorted(times) and (chunk.message_start_time, chunk.message_end_time) == (times[0], times[-1])
    # in file order, only the late messages are older than one written before them
    stored = [t for _, times in chunks for t in times]
    older = sum(1 for i, t in enumerate(stored) if i and t < max(stored[:i]))
    assert older == 3, older
    offset = int(read_metadata(segment)["roadlog"][LOG_TIME_OFFSET_KEY])
    assert wall_before - 20 * S < min(stored) and max(stored) < wall_after  # UTC, from the backlog's start on
    assert min(stored) - offset == min(m.host_mono_ns for msgs in sent.values() for m in msgs)


def test_the_typescript_mcap_reader_sees_every_chunk_in_log_time_order(recorded_segment, node_mcap):
    segment, _, _, _ = recorded_segment
    seen = typescript_chunks(node_mcap, segment)
    assert seen["done"] and seen["messages_outside_chunks"] == 0
    total = 0
    for chunk in seen["chunks"]:
        times = [int(t) for t in chunk["log_times"]]
        assert times == sorted(times), chunk["topics"][:5]
        assert (int(chunk["start"]), int(chunk["end"])) == (times[0], times[-1])
        total += len(times)
    assert total == len(list(read_log([segment]))) + 4  # and the three camera calibrations, the static transforms


def test_a_topic_published_seconds_after_its_stamps_holds_no_sensor_message_back(tmp_path):
    """Fused poses come out ~2.5 s after the time they are the pose of (vehicle_pose): the recorder writes them in
    chunks of their own, so the IMU samples around them are written at once, not held back with them (a power cut
    would lose them), and every chunk stays in log-time order with nothing counted late."""
    config_path = write_config(tmp_path)
    config = load_config(config_path)
    out = tmp_path / "logs"
    imu_pub, pose_pub = pubsub.open_publisher(config, IMU), pubsub.open_publisher(config, VEHICLE_POSE)
    lag_ns = int((POSE_STAMP_LAG_S - 0.5) * S)
    try:
        rec = RecorderProcess(config_path, out)
        n_imu = n_pose = 0
        end = time.monotonic() + 6.0
        while time.monotonic() < end:
            imu_pub.publish(ImuSample(sensor_time_ns=n_imu, accel_mps2=(0.0, 0.0, 9.81)))
            n_imu += 1
            if n_imu % 20 == 0:
                stamp = time.monotonic_ns() - lag_ns
                pose_pub.publish(VehiclePose(sensor_time_ns=stamp, host_mono_ns=stamp, frame_id="map"))
                n_pose += 1
            time.sleep(0.005)
        detail = rec.wait_written({IMU: n_imu, VEHICLE_POSE: n_pose})
        assert rec.stop() == 0, rec.stderr
    finally:
        for closing in (imu_pub, pose_pub):
            closing.close()
        while RecorderProcess.started:
            proc = RecorderProcess.started.pop()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        pubsub.unlink_all(config)
    assert detail["late"] == {}
    [segment] = sorted(out.glob("*.mcap"))
    topics = [rec.topic for rec in read_log([segment])]
    assert topics.count(IMU) == n_imu and topics.count(VEHICLE_POSE) == n_pose
    chunks = chunks_in_file_order(segment)
    for chunk, times in chunks:
        assert times == sorted(times) and (chunk.message_start_time, chunk.message_end_time) == (times[0], times[-1])
    # in file order, the poses (and their transforms) come after IMU samples up to ~2.5 s newer: they were not waited
    # for; those still held when the recorder stopped are merged in order (the last ~2-4 s of the drive's poses)
    stored = [t for _, times in chunks for t in times]
    written_after_newer = sum(1 for i, t in enumerate(stored) if i and t < max(stored[:i]))
    assert written_after_newer >= n_pose, (written_after_newer, n_pose)
