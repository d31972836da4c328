"""Log times in UTC: a new file's MCAP log times are UTC (host_mono_ns + the file's one offset), every reader still
gets host monotonic times, and a log written before the change (tests/data/monotonic_clock_log.mcap, written by the
writer of commit ea531c3 with tests.daemon.test_log_format._messages(2)) reads, replays and recovers as it did."""

from __future__ import annotations

import time
from pathlib import Path

from mcap.reader import make_reader

from daemon.bus import pubsub
from daemon.commands.log_info import summarise
from daemon.log_format.metadata_records import CHANNEL_OFFSET_KEY, LOG_TIME_CLOCK_KEY, LOG_TIME_OFFSET_KEY
from daemon.log_format.reader import ReadReport, last_log_time, read_log, read_metadata
from daemon.log_format.recovery import recover_log
from daemon.log_format.writer import LogWriter
from daemon.processes.replay import log_span, replay
from daemon.spine.config import load_config
from tests.daemon.test_log_format import CONFIG, _messages
from tests.daemon.test_recorder import write_config

S = 1_000_000_000
OLD_LOG = Path(__file__).resolve().parents[1] / "data" / "monotonic_clock_log.mcap"


def raw_messages(path: Path) -> list[tuple[str, int, dict]]:
    """(topic, MCAP log time, channel metadata) in file order, by the mcap library."""
    with open(path, "rb") as f:
        records = make_reader(f).iter_messages(log_time_order=False)
        return [(c.topic, m.log_time, dict(c.metadata)) for _, c, m in records]


def write_new(path: Path, msgs) -> LogWriter:
    with LogWriter(path, CONFIG, chunk_size=32 * 1024) as writer:
        for topic, msg in msgs:
            writer.write(topic, msg)
    return writer


def test_a_new_file_has_utc_log_times_and_gives_host_times_back(tmp_path):
    msgs = _messages(3)
    path = tmp_path / "new.mcap"
    before = time.time_ns() - time.monotonic_ns()
    writer = write_new(path, msgs)
    after = time.time_ns() - time.monotonic_ns()
    meta = read_metadata(path)["roadlog"]
    offset = int(meta[LOG_TIME_OFFSET_KEY])
    assert meta[LOG_TIME_CLOCK_KEY] == "utc" and offset == writer.log_time_offset_ns
    assert before - 10**6 <= offset <= after + 10**6  # UTC minus monotonic when the file was opened
    raw = raw_messages(path)
    assert all(int(channel[CHANNEL_OFFSET_KEY]) == offset for _, _, channel in raw)
    host_times = {(t, m.host_mono_ns) for t, m in msgs}
    views = ("calibration/", "tf_static")  # written with the first message
    data = [(t, log_time) for t, log_time, _ in raw if not t.startswith(views)]
    assert {(t, log_time - offset) for t, log_time in data} == host_times
    assert all(1.6e18 < log_time <= time.time_ns() for _, log_time, _ in raw)  # a date of this decade, not 1970
    calibrations = [log_time for t, log_time, _ in raw if t.startswith(views)]
    assert calibrations == [min(m.host_mono_ns for _, m in msgs) + offset] * 4
    back = list(read_log([path]))
    assert [(r.topic, r.log_time_ns, r.message) for r in back] == [(t, m.host_mono_ns, m) for t, m in msgs]
    assert last_log_time(path) == max(m.host_mono_ns for _, m in msgs)
    middle = msgs[len(msgs) // 2][1].host_mono_ns  # start/end are host times too
    assert [r.message for r in read_log([path], start_ns=middle)] == [m for _, m in msgs if m.host_mono_ns >= middle]


def test_a_log_written_on_the_monotonic_clock_reads_as_before(tmp_path):
    msgs = _messages(2)
    meta = read_metadata(OLD_LOG)["roadlog"]
    assert LOG_TIME_CLOCK_KEY not in meta  # the writer before UTC log times
    assert {log_time for t, log_time, _ in raw_messages(OLD_LOG) if t.startswith("calibration/")} == {0}
    old = [(r.topic, r.log_time_ns, r.message) for r in read_log([OLD_LOG])]
    assert old == [(t, m.host_mono_ns, m) for t, m in msgs]
    new = tmp_path / "new.mcap"
    write_new(new, msgs)
    assert [(r.topic, r.log_time_ns, r.message) for r in read_log([new])] == old
    assert last_log_time(OLD_LOG) == last_log_time(new)
    span_old, span_new = log_span([OLD_LOG]), log_span([new])
    assert (span_old.start_ns, span_old.end_ns) == (span_new.start_ns, span_new.end_ns)
    # an old log and a new one of the same drive merge by host time
    assert [r.log_time_ns for r in read_log([OLD_LOG, new])] == sorted(2 * [m.host_mono_ns for _, m in msgs])


def test_an_unclosed_log_of_the_old_format_recovers_into_utc_log_times(tmp_path):
    src = tmp_path / "old.mcap.open"
    data = OLD_LOG.read_bytes()
    src.write_bytes(data[: len(data) * 2 // 3])  # a writer killed mid-file: no summary, no footer
    intact = [(r.topic, r.log_time_ns, r.message) for r in read_log([src])]
    assert intact
    fixed = tmp_path / "old.mcap"
    report = recover_log(src, fixed, CONFIG)
    assert report.messages == len(intact)
    meta = read_metadata(fixed)["roadlog"]
    offset = int(meta[LOG_TIME_OFFSET_KEY])
    assert meta[LOG_TIME_CLOCK_KEY] == "utc" and offset == 1763000000000000000 - 900000000  # its start times' pair
    assert [(r.topic, r.log_time_ns, r.message) for r in read_log([fixed])] == intact
    assert [log_time - offset for t, log_time, _ in raw_messages(fixed) if t == "imu"] == [
        host for t, host, _ in intact if t == "imu"]


def replayed_imu(tmp_path: Path, path: Path) -> list:
    """The IMU samples a replay of `path` publishes (the real player, at its own pace, into a fresh bus)."""
    folder = tmp_path / path.stem
    folder.mkdir()
    config = load_config(write_config(folder))
    try:
        progress = replay(config, [path], rate=None)
        assert progress.report.incomplete_files == [] and progress.published["imu"] == 2
        sub = pubsub.open_subscriber(config, "imu", start="oldest")
        got = []
        while (msg := sub.read(timeout_s=0, copy=True)) is not None:
            got.append(msg)
        sub.close()
        return got
    finally:
        pubsub.unlink_all(config)


def test_an_old_log_and_a_new_one_replay_the_same(tmp_path):
    """The player paces and stamps by host times: the old and the new file of one drive publish the same messages
    at the same host-time spacing."""
    new = tmp_path / "new.mcap"
    write_new(new, _messages(2))
    old_imu, new_imu = replayed_imu(tmp_path, OLD_LOG), replayed_imu(tmp_path, new)
    assert [m.accel_mps2 for m in old_imu] == [m.accel_mps2 for m in new_imu] and len(old_imu) == 2
    assert old_imu[1].host_mono_ns - old_imu[0].host_mono_ns == new_imu[1].host_mono_ns - new_imu[0].host_mono_ns
    # these stamps lie within a second of their host times: on the host clock, moved with them in both
    assert [m.sensor_time_ns - m.host_mono_ns for m in old_imu] == [m.sensor_time_ns - m.host_mono_ns for m in new_imu]


def test_read_report_of_an_old_log_is_complete():
    report = ReadReport()
    assert len(list(read_log([OLD_LOG], report=report))) == 24
    assert report.files[0].complete and report.files[0].undecodable == 0


def test_log_info_names_the_clock_and_gives_the_same_span_for_both(tmp_path):
    new = tmp_path / "new.mcap"
    write_new(new, _messages(2))
    old_info, new_info = summarise([str(OLD_LOG)]), summarise([str(new)])
    assert old_info["recorded"]["log_time_clock"] == "host_monotonic"
    assert new_info["recorded"]["log_time_clock"] == "utc"
    assert old_info["duration_s"] == new_info["duration_s"] > 0
    assert old_info["messages_per_topic"] == new_info["messages_per_topic"]


def test_a_simulated_drive_opens_on_its_utc_date_and_spans_only_the_drive(city_drive):
    """What Foxglove's timeline shows: the summary's first and last log time (calibrations and transforms included)
    span the drive from its UTC start, not 1970 to an hour later."""
    with open(city_drive, "rb") as f:
        stats = make_reader(f).get_summary().statistics
    meta = read_metadata(city_drive)["roadlog"]
    assert stats.message_start_time == int(meta["start_time_utc_ns"])
    assert (stats.message_end_time - stats.message_start_time) / S < 5.0 + 2.0  # the 5 s drive, its last anchor
    first = next(read_log([city_drive]))
    assert first.log_time_ns == int(meta["start_mono_ns"])  # host times as before


def test_an_unclosed_new_log_recovers_with_its_own_offset(tmp_path):
    closed = tmp_path / "new.mcap"
    write_new(closed, _messages(3))
    src = tmp_path / "new.mcap.open"
    data = closed.read_bytes()
    src.write_bytes(data[: len(data) * 2 // 3])
    fixed = tmp_path / "fixed.mcap"
    report = recover_log(src, fixed, CONFIG)
    assert report.messages > 0
    assert read_metadata(fixed)["roadlog"][LOG_TIME_OFFSET_KEY] == read_metadata(closed)["roadlog"][LOG_TIME_OFFSET_KEY]
    kept = {(t, log_time) for t, log_time, _ in raw_messages(fixed) if t.startswith("camera/")}
    assert kept and kept <= {(t, log_time) for t, log_time, _ in raw_messages(closed)}  # the same UTC log times
    assert [(r.topic, r.log_time_ns, r.message) for r in read_log([fixed])] == [
        (r.topic, r.log_time_ns, r.message) for r in read_log([src])]  # the images' host times too
