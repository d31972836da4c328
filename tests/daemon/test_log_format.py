"""The MCAP log format: every message type round-trips; truncated files read back their complete prefix."""

import json
import os
import random
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader

from daemon.log_format.reader import ReadReport, read_log, read_metadata, summary_message_counts
from daemon.log_format.recovery import recover_log
from daemon.log_format.writer import LogWriter
from daemon.spine.config import load_config
from daemon.spine.messages import (
    MESSAGE_TYPES,
    CameraFrame,
    CanFrame,
    DriverHealth,
    GnssFix,
    GnssVelocity,
    ImuSample,
    LidarPacket,
    PointCloud,
    SemanticMask,
    TimeAnchor,
    VehiclePose,
    WheelSpeeds,
)

CONFIG = load_config(Path(__file__).resolve().parents[2] / "configs" / "sim.yaml")


def _messages(n_rounds: int = 3) -> list[tuple[str, object]]:
    rng = random.Random(7)
    out = []
    t = 1_000_000_000
    for i in range(n_rounds):
        batch = [
            ("camera/front_wide", CameraFrame(i, t + 1, 0, "front_wide", "jpeg", 0, 0, rng.randbytes(2000))),
            ("camera/front_left", CameraFrame(i, t + 2, 0, "front_left", "rgb8", 4, 2, rng.randbytes(24))),
            ("camera/front_right", CameraFrame(i, t + 3, 0, "front_right", "h265", 0, 0, rng.randbytes(500))),
            ("mask/front_wide", SemanticMask(i, t + 4, 0, "front_wide", "png", rng.randbytes(300))),
            ("lidar/packets", LidarPacket(i, t + 5, 0, "lidar", rng.randbytes(24896))),
            ("gnss/fix", GnssFix(i, t + 6, 0, 48.1 + i, 11.5, 520.25, tuple(rng.random() for _ in range(9)), 3)),
            ("imu", ImuSample(i, t + 7, 0, (0.1, -0.2, 9.81), (0.001, 0.002, -0.003))),
            ("wheel_speeds", WheelSpeeds(i, t + 8, 0, 10.0, 10.1, 9.9, 10.05, 0.02)),
            ("can/frames", CanFrame(i, t + 9, 0, 0x217, False, i == 1, False, "can0", rng.randbytes(8))),
            ("pose", VehiclePose(i, t + 10, 0, "enu", (1.5, -2.25, 0.125), (0.0, 0.0, 0.38268343, 0.92387953))),
            ("health/lidar", DriverHealth(i, t + 11, 0, "lidar", "degraded", 9.5, 0.2, 10, 9, 1, 2, 3, 4, "gap")),
            ("time_anchor", TimeAnchor(i, t + 12, 0, 1_763_000_000_000_000_000 + i)),
        ]
        for k, (_, msg) in enumerate(batch):
            msg.host_mono_ns = t + 100 + k
        out += batch
        t += 100_000_000
    return out


def test_every_message_type_round_trips(tmp_path):
    msgs = _messages()
    # (not in _messages: tests/data's logs of an older writer hold those, and no velocity)
    covariance = (0.0025, 0.0, 0.0, 0.0, 0.0025, 0.0, 0.0, 0.0, 0.01)
    velocity = GnssVelocity(3, 1_350_000_006, 1_350_000_106, (1.25, -0.5, 0.0625), covariance, 2)
    msgs.append(("gnss/velocity", velocity))
    # a PointCloud travels in a point-cloud Lidar's logs instead of packets: tests/daemon/test_point_cloud_log.py
    assert {type(m) for _, m in msgs} | {PointCloud} == set(MESSAGE_TYPES)
    path = tmp_path / "a.mcap"
    with LogWriter(path, CONFIG) as writer:
        for topic, msg in msgs:
            writer.write(topic, msg)
    back = [(r.topic, r.message) for r in read_log([path])]
    assert back == msgs
    meta = read_metadata(path)
    assert "front_wide" in meta["roadlog"]["calibration"]
    assert "mapper:" in meta["roadlog"]["config"]


def test_foxglove_well_known_schemas(tmp_path):
    path = tmp_path / "a.mcap"
    with LogWriter(path, CONFIG) as writer:
        for topic, msg in _messages(1):
            writer.write(topic, msg)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    schema_of = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schema_of["camera/front_wide"] == "foxglove.CompressedImage"
    assert schema_of["camera/front_left"] == "foxglove.RawImage"
    assert schema_of["camera/front_right"] == "foxglove.CompressedVideo"
    assert schema_of["gnss/fix"] == "foxglove.LocationFix"
    assert schema_of["pose"] == "foxglove.PoseInFrame"
    assert schema_of["calibration/front_wide"] == "foxglove.CameraCalibration"
    assert schema_of["lidar/packets"] == "roadlog.LidarPacket"


def test_several_files_merge_in_log_time_order_and_filter_topics(tmp_path):
    msgs = _messages(4)
    paths = [tmp_path / "b.mcap", tmp_path / "a.mcap"]
    writers = [LogWriter(p, CONFIG) for p in paths]
    for i, (topic, msg) in enumerate(msgs):
        writers[i % 2].write(topic, msg)
    for w in writers:
        w.close()
    back = list(read_log(paths))
    assert [r.log_time_ns for r in back] == sorted(m.host_mono_ns for _, m in msgs)
    only = list(read_log(paths, topics=["imu", "pose"]))
    assert {r.topic for r in only} == {"imu", "pose"} and len(only) == 8
    window = list(read_log(paths, start_ns=msgs[12][1].host_mono_ns, end_ns=msgs[24][1].host_mono_ns))
    assert len(window) == 12


def test_write_rejects_unknown_topic_or_wrong_type(tmp_path):
    with LogWriter(tmp_path / "a.mcap", CONFIG) as writer:
        with pytest.raises(KeyError):
            writer.write("no/such/topic", TimeAnchor())
        with pytest.raises(TypeError):
            writer.write("imu", TimeAnchor())


def test_truncated_file_reads_complete_prefix_without_exception(tmp_path):
    msgs = _messages(30)
    path = tmp_path / "full.mcap"
    with LogWriter(path, CONFIG, chunk_size=16 * 1024) as writer:
        for topic, msg in msgs:
            writer.write(topic, msg)
    data = path.read_bytes()
    rng = random.Random(3)
    cuts = sorted({rng.randrange(0, len(data)) for _ in range(25)} | {0, 8, len(data) - 1})
    previous = -1
    for cut in cuts:
        cut_path = tmp_path / "cut.mcap"
        cut_path.write_bytes(data[:cut])
        report = ReadReport()
        back = [(r.topic, r.message) for r in read_log([cut_path], report=report)]
        assert not report.files[0].complete
        assert report.files[0].bytes_skipped <= cut
        # what comes back is exactly a prefix-closed subset of what was written, and grows with the cut
        assert all(item in msgs for item in back)
        assert len(back) >= previous
        previous = len(back)
    assert previous > len(msgs) * 0.8


def test_recover_log_makes_a_readable_closed_file(tmp_path):
    msgs = _messages(20)
    path = tmp_path / "open.mcap"
    with LogWriter(path, CONFIG, metadata={"start_time_utc_ns": "123", "daemon_run": "7:42"},
                   chunk_size=8 * 1024) as writer:
        for topic, msg in msgs:
            writer.write(topic, msg)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.7)])
    fixed = tmp_path / "fixed.mcap"
    kept = recover_log(path, fixed, CONFIG)
    assert not kept.complete and kept.messages > 0
    report = ReadReport()
    back = list(read_log([fixed], report=report))
    assert report.files[0].complete and len(back) == kept.messages
    meta = read_metadata(fixed)
    assert meta["roadlog"]["recovered_from"] == str(path)
    assert meta["roadlog"]["start_time_utc_ns"] == "123" and meta["roadlog"]["daemon_run"] == "7:42"  # the source's
    last = json.loads(meta["roadlog.counts"]["last_seq_per_topic"])
    assert last and all(seq == max(r.message.seq for r in back if r.topic == t) for t, seq in last.items())
    os.remove(path)


def test_summary_message_counts_of_a_closed_file_and_none_of_a_cut_one(tmp_path):
    msgs = _messages(5)
    path = tmp_path / "full.mcap"
    with LogWriter(path, CONFIG, chunk_size=16 * 1024) as writer:
        for topic, msg in msgs:
            writer.write(topic, msg)
    read = Counter(r.topic for r in read_log([path]))
    counts = summary_message_counts(path)
    assert {t: counts[t] for t in read} == dict(read) and read["lidar/packets"] == 5
    assert set(counts) - set(read) == {"tf_static", *(f"calibration/{c.name}" for c in CONFIG.sensors.cameras)}
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-100])  # no footer: only read_log can count it
    assert summary_message_counts(cut) is None and summary_message_counts(tmp_path / "none.mcap") is None
