"""The recorder as a real process: messages published on the bus end up, all of them, in its MCAP segments.

Rotation by time and by size, crash recovery of an unclosed segment (kill -9), and the disk policy on a
simulated small disk (daemon.processes.disk_policy's ROADLOG_SIMULATED_DISK_BYTES hook), read back with read_log.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
import urllib.request
import uuid
from pathlib import Path

import pytest
import yaml

from daemon.bus import pubsub
from daemon.log_format.reader import read_log, read_metadata
from daemon.log_format.writer import LogWriter
from daemon.processes import disk_policy
from daemon.processes.disk_policy import Segment, deletable, freed, required_free_bytes
from daemon.processes.segment_files import OPEN_SUFFIX, closed_segments, recover_unclosed, segment_name
from daemon.processes.status_server import HealthBoard, make_server
from daemon.spine.config import CarConfig, load_config
from daemon.spine.messages import CameraFrame, CanFrame, ImuSample, LidarPacket
from daemon.spine.process_table import RESTARTS_ENV
from daemon.spine.topics import CAN_FRAMES, IMU, LIDAR_PACKETS, TIME_ANCHOR, camera_topic, health_topic
from tests.daemon.test_log_damage import second_lz4_block_header

ROOT = Path(__file__).resolve().parents[2]
CAMERA = camera_topic("front_wide")


def write_config(tmp_path: Path, **recorder) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"]["shm_prefix"] = f"t{uuid.uuid4().hex[:12]}"
    data["recorder"].update({"min_free_gib": 0.0, "min_free_pct": 0.0}, **recorder)
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class RecorderProcess:
    """`python -m daemon.processes.recorder` with a health subscriber to follow what it did."""

    started: list[subprocess.Popen] = []  # killed at the end of each test, whatever happened

    def __init__(self, config_path: Path, output_dir: Path, env: dict[str, str] | None = None, *args: str):
        self.config = load_config(config_path)
        self.proc = subprocess.Popen([sys.executable, "-m", "daemon.processes.recorder", "--config", str(config_path),
                                      "--output-dir", str(output_dir), *args], cwd=ROOT,
                                     env=dict(os.environ, **(env or {})), stderr=subprocess.PIPE, text=True)
        self.started.append(self.proc)
        self.health = pubsub.open_subscriber(self.config, health_topic("recorder"), start="next", wait_s=20)
        self.detail = self.wait_for(lambda d: True)

    def wait_for(self, condition, timeout_s: float = 15.0) -> dict:
        """The first health detail (JSON) that satisfies `condition`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self.health.read(timeout_s=0.2)
            if msg is not None:
                self.detail = json.loads(msg.detail)
                if condition(self.detail):
                    return self.detail
            assert self.proc.poll() is None, self.proc.stderr.read()
        raise AssertionError(f"recorder health never matched; last: {self.detail}")

    def wait_written(self, expected: dict[str, int]) -> dict:
        return self.wait_for(lambda d: all(d["written"].get(t, 0) >= n for t, n in expected.items()))

    def stop(self, sig=signal.SIGTERM) -> int:
        self.proc.send_signal(sig)
        rc = self.proc.wait(timeout=60)  # draining takes up to DRAIN_LIMIT_S, then the closing fsync (slow disks)
        self.stderr = self.proc.stderr.read()
        self.health.close()
        return rc


@pytest.fixture
def car(tmp_path):
    paths = {}

    def make(**recorder) -> Path:
        paths["config"] = write_config(tmp_path, **recorder)
        return paths["config"]

    yield make
    while RecorderProcess.started:
        proc = RecorderProcess.started.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if "config" in paths:
        pubsub.unlink_all(load_config(paths["config"]))


def publish_drive(config, n_rounds: int, rng: random.Random, sleep_s: float = 0.0) -> dict[str, list]:
    """Publish a small drive: per round a camera frame, 4 Lidar packets, 2 IMU samples, 10 CAN frames."""
    pubs = {t: pubsub.open_publisher(config, t) for t in (CAMERA, LIDAR_PACKETS, IMU, CAN_FRAMES)}
    sent: dict[str, list] = {t: [] for t in pubs}
    t_sensor = 1_000_000_000
    for _ in range(n_rounds):
        batch = [(CAMERA, CameraFrame(sensor_time_ns=t_sensor, camera="front_wide", format="jpeg",
                                      data=rng.randbytes(rng.randrange(20_000, 60_000))))]
        batch += [(LIDAR_PACKETS, LidarPacket(sensor_time_ns=t_sensor + k, data=rng.randbytes(24_896)))
                  for k in range(4)]
        batch += [(IMU, ImuSample(sensor_time_ns=t_sensor + k, accel_mps2=(rng.random(), 0.0, 9.81),
                                  gyro_rps=(0.0, rng.random(), 0.0))) for k in range(2)]
        batch += [(CAN_FRAMES, CanFrame(sensor_time_ns=t_sensor + k, arbitration_id=0x200 + k, channel="can0",
                                        data=rng.randbytes(8))) for k in range(10)]
        for topic, msg in batch:
            pubs[topic].publish(msg)
            sent[topic].append(msg)
        t_sensor += 10_000_000
        if sleep_s:
            time.sleep(sleep_s)
    for p in pubs.values():
        p.close()
    return sent


def recorded(output_dir: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    for rec in read_log(sorted(output_dir.glob("*.mcap"))):
        out.setdefault(rec.topic, []).append(rec.message)
    return out


def test_every_message_is_recorded_and_sigterm_closes_the_segment(car, tmp_path):
    config_path = car()
    config = load_config(config_path)
    out = tmp_path / "logs"
    for t in (CAMERA, LIDAR_PACKETS, IMU, CAN_FRAMES):  # the drivers' rings exist before the recorder
        pubsub.open_publisher(config, t).close()
    rec = RecorderProcess(config_path, out)
    assert rec.detail["recovered"] == [] and rec.detail["disk_full"] is False
    sent = publish_drive(config, 100, random.Random(1))
    detail = rec.wait_written({t: len(m) for t, m in sent.items()})
    assert detail["lost"] == {}
    assert detail["segment"].endswith(".mcap" + OPEN_SUFFIX)
    time.sleep(1.2)  # at least one more time anchor and health message
    assert rec.stop() == 0, rec.stderr
    assert not list(out.glob("*" + OPEN_SUFFIX))
    segments = sorted(out.glob("*.mcap"))
    assert len(segments) == 1
    back = recorded(out)
    for topic, msgs in sent.items():
        assert back[topic] == msgs, topic  # every field, seq and host_mono_ns included
    anchors = back[TIME_ANCHOR]
    assert len(anchors) >= 2 and abs(anchors[-1].utc_ns - time.time_ns()) < 30e9
    assert back[health_topic("recorder")]
    counts = read_metadata(segments[0])["roadlog.counts"]
    assert json.loads(counts["lost_per_topic"]) == {}
    per_topic = json.loads(counts["messages_per_topic"])
    assert all(per_topic[t] == len(m) for t, m in sent.items())


@pytest.mark.parametrize("rotation", ["seconds", "bytes"])
def test_segments_rotate_by_time_and_by_size_and_sort_by_time(car, tmp_path, rotation):
    settings = {"segment_seconds": 0.4} if rotation == "seconds" else {"segment_bytes": 400_000}
    config_path = car(**settings)
    config = load_config(config_path)
    out = tmp_path / "logs"
    rec = RecorderProcess(config_path, out)  # the drivers' topics appear after it started
    sent = publish_drive(config, 60, random.Random(2), sleep_s=0.03)
    rec.wait_written({t: len(m) for t, m in sent.items()})
    assert rec.stop() == 0, rec.stderr
    segments = sorted(out.glob("*.mcap"))
    assert len(segments) >= 4
    first_times = [next(read_log([s], topics=[IMU, LIDAR_PACKETS, CAN_FRAMES])).log_time_ns
                   for s in segments if json.loads(read_metadata(s)["roadlog.counts"]["messages_per_topic"]).get(IMU)]
    assert first_times == sorted(first_times) and len(first_times) >= 3
    for s in segments:
        meta = read_metadata(s)
        assert "front_wide" in meta["roadlog"]["calibration"] and "roadlog.counts" in meta
        if rotation == "bytes":
            assert s.stat().st_size < 400_000 + 200_000
    back = recorded(out)
    for topic, msgs in sent.items():
        assert back[topic] == msgs, topic


def served_status(config: CarConfig) -> dict:
    """/status of a status server reading the bus, once the recorder's health is in it; its /metrics as "metrics"."""
    board = HealthBoard(config)
    board.start()
    server = make_server(config, board, Path("."), port=0)
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with urllib.request.urlopen(base + "/status", timeout=5) as r:
                doc = json.loads(r.read())
            if doc["recorder"]:
                with urllib.request.urlopen(base + "/metrics", timeout=5) as r:
                    return {**doc, "metrics": r.read().decode()}
            time.sleep(0.1)
        raise AssertionError("no recorder health on the status endpoint")
    finally:
        board.stop()
        server.shutdown()
        server.server_close()


def recorded_by_seq(paths: list[Path]) -> dict[tuple[str, int], object]:
    return {(r.topic, r.message.seq): r.message for r in read_log(paths) if r.topic in (CAMERA, LIDAR_PACKETS, IMU,
                                                                                         CAN_FRAMES)}


def test_killed_recorder_leaves_an_open_segment_the_next_start_recovers(car, tmp_path):
    config_path = car()
    config = load_config(config_path)
    out = tmp_path / "logs"
    rec = RecorderProcess(config_path, out)
    sent = publish_drive(config, 120, random.Random(3))  # ~13 MB: several 4 MiB chunks reach the disk
    rec.wait_written({t: len(m) for t, m in sent.items()})
    assert rec.stop(signal.SIGKILL) == -signal.SIGKILL
    unclosed = list(out.glob("*.mcap" + OPEN_SUFFIX))
    assert len(unclosed) == 1 and not list(out.glob("*.mcap"))

    rec = RecorderProcess(config_path, out)
    recovered = rec.detail["recovered"]
    assert len(recovered) == 1 and recovered[0]["from"] == str(unclosed[0])
    assert rec.stop() == 0
    fixed = Path(recovered[0]["to"])
    assert fixed.name == unclosed[0].name[: -len(OPEN_SUFFIX)] and not unclosed[0].exists()
    assert read_metadata(fixed)["roadlog"]["recovered_from"] == str(unclosed[0])
    back = [r.message for r in read_log([fixed], topics=[LIDAR_PACKETS])]
    assert recovered[0]["messages"] > 100
    assert 100 < len(back) <= len(sent[LIDAR_PACKETS])
    assert back == sent[LIDAR_PACKETS][: len(back)]


def test_a_slow_topic_reaches_the_disk_within_a_sync_period_not_when_its_chunk_is_full(car, tmp_path):
    """A car logging only slow topics (IMU and CAN here: ~30 kB, far from a 4 MiB chunk) loses at most a sync period
    to a kill -9 or a power cut: the chunk in progress is finished and fsynced once a second."""
    config_path = car()
    config = load_config(config_path)
    out = tmp_path / "logs"
    rec = RecorderProcess(config_path, out)
    pubs = {t: pubsub.open_publisher(config, t) for t in (IMU, CAN_FRAMES)}
    rng = random.Random(11)
    sent: dict[str, list] = {t: [] for t in pubs}
    for k in range(200):
        for topic, msg in ((IMU, ImuSample(sensor_time_ns=1_000_000_000 + k, accel_mps2=(rng.random(), 0.0, 9.81),
                                           gyro_rps=(0.0, 0.0, 0.0))),
                           (CAN_FRAMES, CanFrame(sensor_time_ns=1_000_000_000 + k, arbitration_id=0x200,
                                                 channel="can0", data=rng.randbytes(8)))):
            pubs[topic].publish(msg)
            sent[topic].append(msg)
    rec.wait_written({t: len(m) for t, m in sent.items()})
    time.sleep(2.5)  # more than a sync period (1 s) after they were written
    assert rec.stop(signal.SIGKILL) == -signal.SIGKILL
    unclosed = list(out.glob("*.mcap" + OPEN_SUFFIX))
    assert len(unclosed) == 1

    rec = RecorderProcess(config_path, out)
    recovered = Path(rec.detail["recovered"][0]["to"])
    assert rec.stop() == 0
    back: dict[str, list] = {}
    for r in read_log([recovered], topics=list(sent)):
        back.setdefault(r.topic, []).append(r.message)
    for topic in sent:
        assert back.get(topic, []) == sent[topic], topic
    for p in pubs.values():
        p.close()


def test_a_torn_unclosed_segment_is_quarantined_its_intact_chunks_recovered_and_recording_goes_on(car, tmp_path):
    """A power cut's torn write (a zeroed 4 KiB block) in the unclosed segment: the next start keeps the segment
    as it is as `.mcap.damaged`, recovers every chunk but the torn one, reports it and records on (it used to
    die on the lz4 error at every start)."""
    config_path = car()
    config = load_config(config_path)
    out = tmp_path / "logs"
    rec = RecorderProcess(config_path, out)
    sent = publish_drive(config, 120, random.Random(3))  # ~13 MB: three 4 MiB chunks reach the disk
    rec.wait_written({t: len(m) for t, m in sent.items()})
    assert rec.stop(signal.SIGKILL) == -signal.SIGKILL
    [unclosed] = out.glob("*.mcap" + OPEN_SUFFIX)
    intact = recorded_by_seq([unclosed])  # what its chunks hold
    torn = bytearray(unclosed.read_bytes())
    block = second_lz4_block_header(bytes(torn)) // 4096 * 4096  # lz4 raised RuntimeError on it
    torn[block:block + 4096] = bytes(4096)
    unclosed.write_bytes(torn)

    rec = RecorderProcess(config_path, out)
    [report] = rec.detail["recovered"]
    quarantined = Path(report["quarantined"])
    assert quarantined.name == unclosed.name[: -len(OPEN_SUFFIX)] + ".damaged" and not unclosed.exists()
    assert quarantined.read_bytes() == torn  # kept as it was
    assert rec.detail["segments_quarantined"] == 1 and "quarantined" in rec.detail["last_error"]
    assert report["damaged_chunks"] == 1 and report["bytes_skipped"] >= 4096 and report["error"]
    back = recorded_by_seq([Path(report["to"])])
    assert all(back[k] == intact[k] for k in back) and 0 < len(intact) - len(back) < len(intact) / 2
    for topic in {t for t, _ in intact}:  # the first chunk is torn: each topic lost its first messages, nothing after
        seqs = [seq for t, seq in sorted(intact) if t == topic]
        missing = [seq for seq in seqs if (topic, seq) not in back]
        assert missing == seqs[:len(missing)], topic
    status = served_status(config)  # the status endpoint shows it, from the recorder's health on the bus
    assert status["recorder"]["segments_quarantined"] == 1
    assert status["recorder"]["recovered"][0]["quarantined"] == str(quarantined)
    assert "roadlog_recorder_segments_quarantined_total 1.0" in status["metrics"]
    more = publish_drive(config, 10, random.Random(4))
    rec.wait_written({t: len(m) for t, m in more.items()})
    assert rec.stop() == 0
    assert f"quarantined {unclosed.name} as {quarantined.name}" in rec.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted([quarantined.name, Path(report["to"]).name] + [
        p.name for p in out.glob("*.mcap") if p.name != Path(report["to"]).name])
    assert len(list(out.glob("*.mcap"))) == 2  # the recovered segment and the new one


def test_power_cuts_at_random_offsets_are_recovered_or_quarantined_never_lost(tmp_path):
    """recover_unclosed (what the recorder runs at start) on 30 segments cut at random offsets, the last blocks
    before the cut torn (zeroed or stale bytes): none raises; each gives a closed NAME.mcap with every message
    read_log finds intact in the cut file; a cut file with unreadable bytes is kept as it was as .mcap.damaged,
    one read in full (a cut between chunks) is removed."""
    config = load_config(ROOT / "configs" / "sim.yaml")
    rng = random.Random(30)
    base = tmp_path / "base.mcap"
    writer = LogWriter(base, config, chunk_size=64 * 1024)
    for i in range(200):
        writer.write(LIDAR_PACKETS, LidarPacket(seq=i, sensor_time_ns=i, host_mono_ns=10**9 + i,
                                                data=rng.randbytes(rng.choice((3000, 24_896)))))
        writer.write(IMU, ImuSample(seq=i, sensor_time_ns=i, host_mono_ns=10**9 + i, accel_mps2=(0.0, 0.0, 9.8)))
    writer.flush()
    data = base.read_bytes()
    out = tmp_path / "logs"
    out.mkdir()
    cut_files = {}
    for k in range(30):
        cut = bytearray(data[:rng.randrange(100, len(data))] if k >= 2 else data)  # two end at a chunk's end
        for _ in range(rng.randrange(0, 3) if k >= 2 else 0):
            at = max(0, len(cut) - rng.randrange(1, 8) * 4096)
            at -= at % 4096
            cut[at:at + 4096] = bytes(4096) if rng.random() < 0.5 else rng.randbytes(4096)
            del cut[len(data):]
        src = out / (segment_name(10**18, k) + OPEN_SUFFIX)
        src.write_bytes(cut)
        cut_files[src] = (bytes(cut), [(r.topic, r.message) for r in read_log([src])])
    reports = recover_unclosed(out, config)
    assert len(reports) == 30 and not list(out.glob("*" + OPEN_SUFFIX))
    for report in reports:
        src = Path(report["from"])
        cut, intact = cut_files[src]
        assert [(r.topic, r.message) for r in read_log([Path(report["to"])])] == intact
        if report["quarantined"]:
            assert report["bytes_skipped"] or report["damaged_chunks"]
            assert Path(report["quarantined"]).read_bytes() == cut
        else:
            assert report["bytes_skipped"] == 0 and not src.exists()
    assert [r["quarantined"] is None for r in reports[:2]] == [True, True]  # read in full: nothing kept


def test_a_restarted_recorder_records_what_was_published_while_it_was_down_once(car, tmp_path):
    config_path = car()
    config = load_config(config_path)
    out = tmp_path / "logs"
    for t in (CAMERA, LIDAR_PACKETS, IMU, CAN_FRAMES):
        pubsub.open_publisher(config, t).close()
    rec = RecorderProcess(config_path, out, env={RESTARTS_ENV: "0"})
    before = publish_drive(config, 60, random.Random(5))
    rec.wait_written({t: len(m) for t, m in before.items()})
    assert rec.stop(signal.SIGKILL) == -signal.SIGKILL  # its open chunk (the newest messages) is torn off
    while_down = publish_drive(config, 40, random.Random(6))
    # the supervisor's restart (same daemon run: same parent); it recovers the crash's segment first
    rec = RecorderProcess(config_path, out, env={RESTARTS_ENV: "1"})
    after = publish_drive(config, 20, random.Random(7))
    rec.wait_written({t: len(after[t]) for t in after})
    assert rec.stop() == 0
    assert len(rec.detail["recovered"]) == 1 and rec.detail["lost"] == {}
    back = recorded(out)
    for topic in before:
        assert back[topic] == before[topic] + while_down[topic] + after[topic], topic  # each once, in order


def test_disk_policy_deletes_oldest_closed_segments_then_stops_and_resumes(car, tmp_path):
    disk = 4_000_000
    config_path = car(segment_bytes=300_000, min_free_pct=25.0, keep_newest_s=0)  # keep 1 MB of a 4 MB disk free
    config = load_config(config_path)
    out = tmp_path / "logs"
    rec = RecorderProcess(config_path, out, env={disk_policy.SIMULATED_DISK_ENV: str(disk)})
    lidar = pubsub.open_publisher(config, LIDAR_PACKETS)
    rng = random.Random(4)

    def publish(n: int) -> list:
        msgs = [LidarPacket(sensor_time_ns=i, data=rng.randbytes(24_896)) for i in range(n)]
        for m in msgs:
            lidar.publish(m)
            time.sleep(0.015)  # 1.7 MB/s: the policy deletes one segment first, more once their space stayed free
        return msgs

    publish(250)  # 6 MB through a disk that holds 3 MB
    rec.wait_for(lambda d: d["written"].get(LIDAR_PACKETS, 0) == 250 and d["segments_deleted"] > 0)
    names = sorted(p.name for p in out.glob("*.mcap"))
    # over the target by at most a segment and what was written while the last deletion was judged
    assert names and sum(p.stat().st_size for p in out.iterdir()) <= disk - 1_000_000 + 300_000 + 900_000

    (out / "ballast.bin").write_bytes(b"\0" * 3_500_000)  # someone else fills the disk, once
    rec.wait_for(lambda d: d["disk_full"] and d["disk_policy"]["at_floor"])  # (after a hold-off if it looked taken)
    assert not list(out.glob("*.mcap")), "every closed segment is deleted before writing stops"
    publish(20)
    detail = rec.wait_for(lambda d: d["dropped_disk_full"].get(LIDAR_PACKETS, 0) == 20)
    assert detail["segment"] is None and detail["lost"][LIDAR_PACKETS] == 20

    (out / "ballast.bin").unlink()
    rec.wait_for(lambda d: not d["disk_full"])
    last = publish(10)
    rec.wait_for(lambda d: d["written"][LIDAR_PACKETS] == 260)
    lidar.close()
    assert rec.stop() == 0, rec.stderr
    segments = sorted(out.glob("*.mcap"))
    assert names[0] not in {s.name for s in segments}
    assert [r.message for r in read_log(segments, topics=[LIDAR_PACKETS])] == last
    lost = json.loads(read_metadata(segments[0])["roadlog.counts"]["lost_per_topic"])
    assert lost[LIDAR_PACKETS] == 20  # (besides the recorder's own anchors and health of that time)
    assert set(lost) <= {LIDAR_PACKETS, TIME_ANCHOR, health_topic("recorder")}


def with_a_three_packet_lidar_ring(config_path: Path) -> tuple[Path, CarConfig]:
    """The config rewritten with a Lidar ring that holds 3 packets: a burst overruns a normal reader."""
    data = yaml.safe_load(config_path.read_text())
    data["bus"]["ring_bytes"] = {LIDAR_PACKETS: 100_000}
    config_path.write_text(yaml.safe_dump(data))
    return config_path, load_config(config_path)


def test_messages_the_bus_overwrote_before_the_recorder_read_them_are_counted(car, tmp_path):
    config_path, config = with_a_three_packet_lidar_ring(car())
    out = tmp_path / "logs"
    lidar = pubsub.open_publisher(config, LIDAR_PACKETS)
    rec = RecorderProcess(config_path, out)
    payload = random.Random(8).randbytes(24_896)
    for i in range(300):  # a burst far faster than the recorder polls
        lidar.publish(LidarPacket(sensor_time_ns=i, data=payload))
    detail = rec.wait_for(lambda d: d["written"].get(LIDAR_PACKETS, 0) + d["lost"].get(LIDAR_PACKETS, 0) == 300)
    lidar.close()
    assert detail["lost_bus"][LIDAR_PACKETS] > 0 and detail["lost"] == detail["lost_bus"]
    assert rec.stop() == 0, rec.stderr
    segments = sorted(out.glob("*.mcap"))
    written = [r.message.sensor_time_ns for r in read_log(segments, topics=[LIDAR_PACKETS])]
    lost = json.loads(read_metadata(segments[-1])["roadlog.counts"]["lost_per_topic"])
    assert len(written) + lost[LIDAR_PACKETS] == 300 and written == sorted(written) and written[-1] == 299


def test_a_lossless_recorder_makes_a_lossless_publisher_wait_and_records_everything(car, tmp_path):
    config_path, config = with_a_three_packet_lidar_ring(car())
    out = tmp_path / "logs"
    lidar = pubsub.open_publisher(config, LIDAR_PACKETS)
    rec = RecorderProcess(config_path, out, None, "--lossless")  # its first health: its subscribers are open
    payload = random.Random(9).randbytes(24_896)
    for i in range(300):  # the same burst that overruns a normal recorder: now the publisher waits
        lidar.publish(LidarPacket(sensor_time_ns=i, data=payload), lossless=True, timeout_s=10.0)
    detail = rec.wait_written({LIDAR_PACKETS: 300})
    lidar.close()
    assert detail["lost"].get(LIDAR_PACKETS, 0) == 0
    assert rec.stop() == 0, rec.stderr
    written = [r.message.sensor_time_ns for r in read_log(sorted(out.glob("*.mcap")), topics=[LIDAR_PACKETS])]
    assert written == list(range(300))


def test_disk_policy_pure_functions():
    gib = disk_policy.GIB
    assert required_free_bytes(100 * gib, 5.0, 10.0) == 10 * gib
    assert required_free_bytes(20 * gib, 5.0, 10.0) == 5 * gib
    segs = [Segment(Path(f"s{i}"), 100) for i in range(5)]
    assert deletable(segs, lambda seg: 10.0, keep_newest_s=0) == segs
    assert deletable(segs, lambda seg: 10.0, keep_newest_s=15) == segs[:3]  # the newest two hold the 15 s
    assert deletable(segs, lambda seg: 10.0, keep_newest_s=1000) == []
    assert freed(1000, 1100, 0, 100) and freed(1000, 990, 90, 100)  # (our own writes took 90 meanwhile)
    assert not freed(1000, 1000, 0, 100) and not freed(1000, 1040, 0, 100)


def test_segment_names_sort_by_time(tmp_path):
    t = 1_795_000_000_000_000_000
    names = [segment_name(t, 9), segment_name(t + 1_000_000_000, 10), segment_name(t + 61_000_000_000, 11)]
    assert names == sorted(names) and names[0].startswith("roadlog_2026")
    for n in names:
        (tmp_path / n).write_bytes(b"x")
    (tmp_path / (segment_name(t, 12) + OPEN_SUFFIX)).write_bytes(b"x")
    assert [s.path.name for s in closed_segments(tmp_path)] == names
    after_clock_reset = segment_name(t - 86400_000_000_000, 13)  # the clock went back a day
    (tmp_path / after_clock_reset).write_bytes(b"x")
    assert [s.path.name for s in closed_segments(tmp_path)] == names + [after_clock_reset]
