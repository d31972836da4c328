"""Segments cut by the log time of their messages, not by the wall clock: a backlog the live recorder reads in one
burst and a replay at rate 1 or `max` are cut at the same messages, read back from the MCAP files; a bad clock
neither cuts a segment per message nor keeps one open (daemon/processes/segment_clock.py)."""

from __future__ import annotations

import json
import re
import time
from datetime import UTC, datetime
from pathlib import Path

from daemon.bus import pubsub
from daemon.log_format.reader import read_log, read_metadata
from daemon.log_format.writer import LogWriter
from daemon.processes.segment_clock import SegmentClock
from daemon.spine.config import load_config
from daemon.spine.messages import CanFrame, ImuSample, TimeAnchor
from daemon.spine.topics import CAN_FRAMES, IMU, TIME_ANCHOR
from tests.daemon.test_recorder import RecorderProcess, car  # noqa: F401 - the fixture
from tests.daemon_fixtures import private_config
from tests.roadlog_cli import can_only_log, roadlog

S = 0.5  # segment_seconds of these tests
S_NS = int(S * 1e9)


def feed_by_segment(folder: Path, topics: tuple[str, ...]) -> list[list[tuple[str, int]]]:
    """Per closed segment (in name order) holding any of `topics`: their (topic, host_mono_ns) as recorded."""
    out = []
    for segment in sorted(folder.rglob("*.mcap")):
        got = [(r.topic, r.message.host_mono_ns) for r in read_log([segment], topics=list(topics))]
        if got:
            out.append(got)
    return out


def test_the_clock_tiles_the_log_time_and_starts_again_after_a_gap():
    clock = SegmentClock(S)
    begins = [clock.begins_segment("imu", t) for t in range(0, 2 * S_NS, S_NS // 5)]
    assert begins == [False] * 5 + [True] + [False] * 4  # the second slot begins at the first message past S
    assert clock.start_ns == S_NS  # where the first slot ended, not at that message: the slots tile the log
    assert clock.begins_segment("imu", 2 * S_NS + 1)  # contiguous: [2S, 3S)
    assert clock.start_ns == 2 * S_NS and clock.gaps == 0
    assert clock.begins_segment("imu", 100 * S_NS + 7)  # no message for many segments: the slot starts here
    assert clock.start_ns == 100 * S_NS + 7 and clock.gaps == 1
    assert not clock.begins_segment("can", 3 * S_NS)  # stamped before its slot: written in it, counted
    assert clock.before_start == {"can": 1}
    assert clock.take_segment_counts() == {"clock_ahead_per_topic": {}, "before_segment_start_per_topic": {"can": 1}}
    assert clock.take_segment_counts()["before_segment_start_per_topic"] == {}


def test_a_live_clock_far_ahead_neither_cuts_a_segment_per_message_nor_keeps_one_open():
    """A topic stamped a day ahead, interleaved with good ones, for 10 s of host time at 100 Hz: live it is taken as
    stamped now, so the segments follow the host's clock (0.5 s each), not one per message nor one for a day."""
    now = [10**12]
    clock = SegmentClock(S, lambda: now[0])
    cuts = 0
    for _ in range(1000):
        now[0] += 10_000_000
        cuts += clock.begins_segment("imu", now[0])
        cuts += clock.begins_segment("bad", now[0] + 86_400 * 10**9)
    assert 19 <= cuts <= 21 and clock.ahead == {"bad": 1000} and clock.gaps == 0
    assert clock.start_ns <= now[0] and clock.before_start == {}


def test_a_live_backlog_read_in_one_burst_is_cut_by_its_own_time(car, tmp_path):  # noqa: F811 - the fixture
    """IMU and CAN messages stamped over 4 x segment_seconds wait in their rings (a driver's backlog) when the live
    recorder starts: it reads them in a fraction of a second and cuts them into exactly 4 segments, each its slot of
    their time (with wall-time rotation they all went into one)."""
    config_path = car(segment_seconds=S)
    config = load_config(config_path)
    out = tmp_path / "logs"
    t0 = time.monotonic_ns() - 20 * S_NS  # stamped in the past: a live host time is never ahead of the clock
    pubs = {t: pubsub.open_publisher(config, t) for t in (IMU, CAN_FRAMES)}
    sent = []
    for i in range(4 * 50):
        t = t0 + i * 10_000_000
        pubs[IMU].publish(ImuSample(sensor_time_ns=t, host_mono_ns=t, accel_mps2=(0.0, 0.0, 9.81)))
        pubs[CAN_FRAMES].publish(CanFrame(sensor_time_ns=t, host_mono_ns=t + 1, arbitration_id=0x100,
                                          channel="can0", data=bytes(8)))
        sent += [(IMU, t), (CAN_FRAMES, t + 1)]
    rec = RecorderProcess(config_path, out)
    rec.wait_written({IMU: 200, CAN_FRAMES: 200})
    assert rec.stop() == 0, rec.stderr
    for p in pubs.values():
        p.close()
    segments = feed_by_segment(out, (IMU, CAN_FRAMES))
    assert [len(s) for s in segments] == [100, 100, 100, 100]
    for k, segment in enumerate(segments):
        assert all(t0 + k * S_NS <= t < t0 + (k + 1) * S_NS for _, t in segment), k
    assert sorted(m for s in segments for m in s) == sorted(sent)
    counts = [read_metadata(p)["roadlog.counts"] for p in sorted(out.glob("*.mcap"))]
    assert all(json.loads(c["before_segment_start_per_topic"]) == {} for c in counts)


def test_a_live_recorder_with_nothing_to_record_still_closes_its_segments_on_time(car, tmp_path):  # noqa: F811
    """No driver publishes: the live recorder's own time anchors (1 Hz) move the clock, so its segments are closed,
    complete on disk, one slot of 1.5 s after another (no endless open segment while the car stands)."""
    config_path = car(segment_seconds=1.5)
    out = tmp_path / "logs"
    rec = RecorderProcess(config_path, out)
    detail = rec.wait_for(lambda d: d["segments_closed"] >= 2, timeout_s=20)
    assert detail["segment_clock"]["gaps"] == 0 and detail["segment_clock"]["ahead"] == {}
    assert rec.stop() == 0, rec.stderr
    closed = sorted(out.glob("*.mcap"))
    assert len(closed) >= 3 and all("roadlog.counts" in read_metadata(p) for p in closed)
    stamps = [datetime.strptime(p.name.split("_")[1], "%Y%m%dT%H%M%SZ").replace(tzinfo=UTC) for p in closed]
    assert all(abs(time.time() - s.timestamp()) < 120 for s in stamps)  # live: named by this host's UTC


def _replayed(log: Path, config_path: Path, out: Path, rate: str, topics: list[str]
              ) -> tuple[list[list[tuple[str, int]]], list[dict[str, int]], str]:
    """`roadlog replay` of the log into `out`: per re-recorded segment holding any of `topics`, their (topic,
    sensor time) in log order; every segment's late count per topic; the daemon's stderr."""
    run = roadlog("replay", str(log), "--config", str(config_path), "--rate", rate, "--output-dir", str(out),
                  timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    segments = sorted(out.rglob("*.mcap"))
    cut = [[(r.topic, r.message.sensor_time_ns) for r in read_log([s], topics=topics)] for s in segments]
    late = [json.loads(read_metadata(s)["roadlog.counts"]["late_per_topic"]) for s in segments]
    return [c for c in cut if c], late, run.stderr


def test_a_replay_is_cut_at_the_same_messages_at_rate_1_4_and_max(tmp_path):
    """`roadlog replay` of a 2.2 s log at rate 1 (2.2 s of wall time), 4 and `max` (a fraction of that) through the
    real daemon: the re-recorded segments hold the same messages, 0.5 s of the log's time each."""
    config, config_path = private_config(tmp_path, mapper={"enabled": False}, status={"port": 0},
                                         recorder={"segment_seconds": S, "min_free_gib": 0.0, "min_free_pct": 0.0})
    log = can_only_log(tmp_path / "drive.mcap", config, frames=220)  # 10 ms apart
    try:
        cut = {rate: [[t for _, t in segment] for segment in _replayed(
            log, config_path, tmp_path / f"rate_{rate}", rate, [CAN_FRAMES])[0]] for rate in ("1", "4", "max")}
    finally:
        pubsub.unlink_all(config)
    expected = [[i * 10_000_000 for i in range(k * 50, min(220, (k + 1) * 50))] for k in range(5)]
    assert cut == {"1": expected, "4": expected, "max": expected}


def _two_topic_log(path: Path, config, frames: int) -> Path:
    """CAN frames and IMU samples interleaved 5 ms apart (each topic every 10 ms), over frames x 10 ms."""
    with LogWriter(path, config) as writer:
        for i in range(frames):
            t = 10**9 + i * 10_000_000
            writer.write(CAN_FRAMES, CanFrame(sensor_time_ns=i * 10_000_000, arbitration_id=0x100, channel="can0",
                                              data=bytes(8), host_mono_ns=t))
            writer.write(IMU, ImuSample(sensor_time_ns=i * 10_000_000 + 5_000_000, host_mono_ns=t + 5_000_000,
                                        accel_mps2=(0.0, 0.0, 9.81)))
    return path


def test_a_slow_replay_of_several_topics_keeps_each_message_in_its_slot(tmp_path):
    """At rate 0.5 the replayed host times fall behind this host's clock; the recorder reads its rings in turn while
    the player publishes them in log-time order, so a message one ring gives after another ring's newer one was
    released would be late and land in the next segment; and the processes' health, stamped on this host's clock,
    runs ahead of them by more than the reorder window (0.3 s here) and must not release them early. Each segment must
    hold exactly its slot's messages of both topics, as at `max`, and nothing be counted late."""
    config, config_path = private_config(tmp_path, mapper={"enabled": False}, status={"port": 0},
                                         recorder={"segment_seconds": S, "min_free_gib": 0.0, "min_free_pct": 0.0,
                                                   "reorder_window_s": 0.3})
    log = _two_topic_log(tmp_path / "drive.mcap", config, frames=120)
    cut = {}
    try:
        for rate in ("0.5", "max"):
            segments, late, _ = _replayed(log, config_path, tmp_path / f"rate_{rate}", rate, [CAN_FRAMES, IMU])
            cut[rate] = [sorted(segment) for segment in segments]
            assert all(not any(d.values()) for d in late), (rate, late)
    finally:
        pubsub.unlink_all(config)
    expected = [sorted([(CAN_FRAMES, i * 10_000_000) for i in range(k * 50, min(120, (k + 1) * 50))]
                       + [(IMU, i * 10_000_000 + 5_000_000) for i in range(k * 50, min(120, (k + 1) * 50))])
                for k in range(3)]
    assert cut == {"0.5": expected, "max": expected}


def test_a_replayed_drive_is_re_recorded_into_segments_named_by_its_own_date(tmp_path):
    """A drive recorded on 2011-09-26 from 13:02:25.2 UTC (its time anchors), replayed today: each re-recorded segment
    is named by the UTC of its first message through those anchors, not by this host's clock."""
    config, config_path = private_config(tmp_path, mapper={"enabled": False}, status={"port": 0},
                                         recorder={"segment_seconds": S, "min_free_gib": 0.0, "min_free_pct": 0.0})
    utc0 = int(datetime(2011, 9, 26, 13, 2, 25, 200_000, tzinfo=UTC).timestamp() * 1e9)
    log = tmp_path / "drive.mcap"
    with LogWriter(log, config) as writer:
        for i in range(220):  # 2.2 s of CAN frames 10 ms apart, an anchor each second
            t = 10**9 + i * 10_000_000
            if i % 100 == 0:
                writer.write(TIME_ANCHOR, TimeAnchor(seq=i // 100, sensor_time_ns=t, host_mono_ns=t,
                                                     utc_ns=utc0 + i * 10_000_000))
            writer.write(CAN_FRAMES, CanFrame(sensor_time_ns=i * 10_000_000, arbitration_id=0x100, channel="can0",
                                              data=bytes(8), host_mono_ns=t))
    try:
        _, _, stderr = _replayed(log, config_path, tmp_path / "replayed", "max", [CAN_FRAMES])
    finally:
        pubsub.unlink_all(config)
    names = sorted(p.name for p in (tmp_path / "replayed").rglob("*.mcap"))
    # slots of 0.5 s from the first message: 25.2, 25.7, 26.2, 26.7 and 27.2 s past 13:02
    stamps = [name.split("_")[1] for name in names]
    assert stamps == ["20110926T130225Z", "20110926T130225Z", "20110926T130226Z", "20110926T130226Z",
                      "20110926T130227Z"], names
    # the recorder's log links each segment as opened (this host's clock) to its closed name
    opened = re.search(rf"closed segment (roadlog_\d{{8}}T\d{{6}}Z_0000\.mcap\.open) as {names[0]}", stderr)
    assert opened and "20110926" not in opened.group(1), stderr[-3000:]
