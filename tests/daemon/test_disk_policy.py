"""The disk policy through the real recorder process on a real small file system: a tmpfs mounted over its output
folder in a private user and mount namespace (`unshare -rm`, skipped where unavailable), reached from here through
/proc/PID/root. Another program that keeps filling the disk costs a few segments, not all of them (the old policy
deleted every closed segment for nothing); the newest `recorder.keep_newest_s` of drive are never deleted; what was
deleted is reported in seconds of drive and bytes on /status, /metrics and in the log."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from daemon.bus import pubsub
from daemon.log_format.reader import read_log
from daemon.processes.disk_policy import SIMULATED_DISK_ENV, STATE_FILE
from daemon.processes.status_server import HealthBoard, make_server
from daemon.spine.config import load_config
from daemon.spine.messages import LidarPacket
from daemon.spine.topics import LIDAR_PACKETS, health_topic
from tests.daemon.test_recorder import ROOT, RecorderProcess, write_config
from tests.daemon.test_ring_reservation import _namespaces_work

ON_TMPFS = pytest.mark.skipif(not _namespaces_work(), reason="unshare -rm (user + mount namespace) unavailable")
MB = 1_000_000


class RecorderOnTmpfs(RecorderProcess):
    """The recorder process with its output folder a fresh tmpfs of `disk_bytes` that only it (and /proc) sees."""

    def __init__(self, config_path: Path, output_dir: Path, disk_bytes: int):
        output_dir.mkdir(parents=True, exist_ok=True)
        self.config = load_config(config_path)
        mount = f'mount -t tmpfs -o size={disk_bytes} roadlog-disk "$1"'
        self.proc = subprocess.Popen(["unshare", "-rm", "sh", "-c", f'{mount} && exec "$0" -m '
                                      'daemon.processes.recorder --config "$2" --output-dir "$1"', sys.executable,
                                      str(output_dir), str(config_path)], cwd=ROOT, stderr=subprocess.PIPE, text=True)
        self.started.append(self.proc)
        self.disk = Path(f"/proc/{self.proc.pid}/root") / str(output_dir).lstrip("/")  # its tmpfs, seen from here
        self.health = pubsub.open_subscriber(self.config, health_topic("recorder"), start="next", wait_s=20)
        self.detail = self.wait_for(lambda d: True)

    def segments(self) -> list[Path]:
        return sorted(self.disk.glob("*.mcap"))


@pytest.fixture
def recorders():
    yield RecorderProcess.started
    while RecorderProcess.started:
        proc = RecorderProcess.started.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def publish(lidar, n: int, rng: random.Random, sleep_s: float = 0.005) -> list[LidarPacket]:
    msgs = [LidarPacket(sensor_time_ns=i, data=rng.randbytes(24_896)) for i in range(n)]
    for m in msgs:
        lidar.publish(m)
        time.sleep(sleep_s)
    return msgs


def fill(path: Path, stop: threading.Event) -> None:
    """Another program: takes every byte the file system frees, until told to stop."""
    chunk = bytes(65536)
    with open(path, "wb", buffering=0) as f:
        while not stop.is_set():
            try:
                f.write(chunk)
            except OSError:  # full: try again in a moment
                time.sleep(0.002)


@ON_TMPFS
def test_another_program_filling_the_disk_costs_a_few_segments_not_all(recorders, tmp_path):
    config_path = write_config(tmp_path, segment_bytes=500_000, min_free_pct=10.0, keep_newest_s=0.5)
    config = load_config(config_path)
    rec = RecorderOnTmpfs(config_path, tmp_path / "logs", 16 * MB)
    lidar = pubsub.open_publisher(config, LIDAR_PACKETS)
    rng = random.Random(5)
    publish(lidar, 300, rng)  # 7.5 MB on a 16 MB disk: no deletion needed
    rec.wait_for(lambda d: d["written"].get(LIDAR_PACKETS, 0) == 300)
    before = [p.name for p in rec.segments()]
    assert len(before) >= 12 and rec.detail["segments_deleted"] == 0

    stop = threading.Event()
    filler = threading.Thread(target=fill, args=(rec.disk / "other-program.bin", stop))
    filler.start()
    try:
        publish(lidar, 300, rng, sleep_s=0.02)  # 6 s of driving while the other program takes every freed byte
        # the disk was full (messages dropped for it: under load the flag may be down again by the next report)
        detail = rec.wait_for(lambda d: d["dropped_disk_full"].get(LIDAR_PACKETS, 0) > 0
                              and d["disk_policy"]["deletions_undone"] >= 1, timeout_s=30.0)
    finally:
        stop.set()
        filler.join()
    policy = detail["disk_policy"]
    left = [p.name for p in rec.segments()]
    assert policy["deletions_undone"] >= 1 and 1 <= policy["deleted_segments"] <= 4, policy  # the old policy: all
    assert len(left) >= len(before) - 4 and set(left) <= set(before)
    assert policy["deleted_bytes"] > 0 and policy["deleted_drive_s"] > 0

    board = HealthBoard(config)
    board.update(rec.health.latest(copy=True))
    server = make_server(config, board, tmp_path, port=0)
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        status = json.loads(urllib.request.urlopen(f"{base}/status", timeout=5).read())
        metrics = urllib.request.urlopen(f"{base}/metrics", timeout=5).read().decode()
    finally:
        server.shutdown()
        server.server_close()
    shown = status["recorder"]["disk_policy"]
    assert shown["deleted_segments"] >= policy["deleted_segments"] and shown["deleted_drive_s"] > 0
    assert 'roadlog_recorder_disk_policy{figure="deleted_drive_s"}' in metrics
    assert 'roadlog_recorder_disk_policy{figure="deleted_bytes"}' in metrics

    os.unlink(rec.disk / "other-program.bin")  # the other program gives its space back: recording resumes
    written = rec.wait_for(lambda d: not d["disk_full"])["written"][LIDAR_PACKETS]
    publish(lidar, 10, rng)
    rec.wait_for(lambda d: d["written"][LIDAR_PACKETS] == written + 10)
    lidar.close()
    kept = [r.message for r in read_log(rec.segments(), topics=[LIDAR_PACKETS])]  # (its tmpfs goes with it)
    assert len(kept) >= 20 * len(left)  # the segments it kept are whole (about 20 packets each)
    assert rec.stop() == 0, rec.stderr
    assert "disk policy: deleted roadlog_" in rec.stderr and "s of drive" in rec.stderr
    assert "another program takes the space" in rec.stderr
    pubsub.unlink_all(config)


@ON_TMPFS
def test_the_newest_recordings_are_never_deleted_to_make_room(recorders, tmp_path):
    config_path = write_config(tmp_path, segment_bytes=500_000, min_free_pct=10.0, keep_newest_s=1000.0)
    config = load_config(config_path)
    rec = RecorderOnTmpfs(config_path, tmp_path / "logs", 8 * MB)
    lidar = pubsub.open_publisher(config, LIDAR_PACKETS)
    publish(lidar, 400, random.Random(6))  # 10 MB of its own drive through an 8 MB disk
    detail = rec.wait_for(lambda d: d["disk_full"] and d["disk_policy"]["at_floor"])
    lidar.close()
    assert detail["disk_policy"]["deleted_segments"] == 0 and detail["segments_deleted"] == 0  # the old: deleted
    assert detail["dropped_disk_full"].get(LIDAR_PACKETS, 0) > 0
    assert rec.stop() == 0, rec.stderr
    assert "recorder.keep_newest_s" in rec.stderr
    pubsub.unlink_all(config)


@pytest.mark.parametrize("value", [-1.0, float("inf"), "five minutes"])
def test_the_floor_is_validated_at_start(tmp_path, value):
    from daemon.spine.config import ConfigError

    with pytest.raises(ConfigError, match="keep_newest_s"):
        load_config(write_config(tmp_path, keep_newest_s=value))


def fill_simulated(folder: Path, disk_bytes: int, stop: threading.Event) -> None:
    """Another program on a simulated disk (SIMULATED_DISK_ENV: the folder is the whole disk): takes every byte
    freed, until told to stop."""
    def size(path: Path) -> int:
        try:
            return path.stat().st_size if path.is_file() else 0
        except FileNotFoundError:  # the recorder renamed or deleted it since the listing (its state file's .tmp)
            return 0

    with open(folder / "other-program.bin", "ab", buffering=0) as f:
        while not stop.wait(0.01):
            used = sum(size(p) for p in folder.iterdir())
            if used < disk_bytes:
                f.write(bytes(disk_bytes - used))


def test_the_deletion_pause_outlives_a_recorder_restart(recorders, tmp_path):
    disk = 16 * MB
    config_path = write_config(tmp_path, segment_bytes=500_000, min_free_pct=10.0, keep_newest_s=0.5,
                               deletion_hold_off_s=[1.0, 300.0])
    config = load_config(config_path)
    logs = tmp_path / "logs"
    env = {SIMULATED_DISK_ENV: str(disk)}
    rec = RecorderProcess(config_path, logs, env)
    lidar = pubsub.open_publisher(config, LIDAR_PACKETS)
    rng = random.Random(7)
    publish(lidar, 300, rng)  # 7.5 MB of a 16 MB disk
    rec.wait_for(lambda d: d["written"].get(LIDAR_PACKETS, 0) == 300)
    stop = threading.Event()
    filler = threading.Thread(target=fill_simulated, args=(logs, disk, stop))
    filler.start()
    try:
        # every deletion's space is taken: held off 1, 2, then 4 s (the config's first hold-off, doubling)
        detail = rec.wait_for(lambda d: d["disk_policy"]["deletions_undone"] >= 3, timeout_s=30)
        assert detail["disk_policy"]["held_off_s"] > 2.0, detail["disk_policy"]
        deleted_before = detail["disk_policy"]["deleted_segments"]
        assert rec.stop() == 0, rec.stderr
        state = json.loads((logs / STATE_FILE).read_text())
        assert state["undone_in_a_row"] == 3

        rec = RecorderProcess(config_path, logs, env)  # the restarted recorder takes up the pause ...
        first = rec.detail["disk_policy"]
        assert first["held_off_s"] > 0 and first["deleted_segments"] == 0, first
        resumed = rec.wait_for(lambda d: d["disk_policy"]["deleted_segments"] > 0, timeout_s=30)
        segments_left = len(list(logs.glob("*.mcap")))
        # ... deletes nothing until it ends, and the next undone deletion holds off longer still (8 s: the 4th)
        detail = rec.wait_for(lambda d: d["disk_policy"]["deletions_undone"] >= 1, timeout_s=15)
        assert detail["disk_policy"]["held_off_s"] > 4.0, detail["disk_policy"]
        assert resumed["disk_policy"]["deleted_segments"] <= 2 and segments_left >= 1
    finally:
        stop.set()
        filler.join()
    lidar.close()
    assert rec.stop() == 0, rec.stderr
    assert "held off for" in rec.stderr
    assert deleted_before <= 4
    pubsub.unlink_all(config)


def test_an_unreadable_pause_file_is_counted_and_ignored(recorders, tmp_path):
    config_path = write_config(tmp_path)
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / STATE_FILE).write_text('{"hold_off_until_unix_s": "soon"')
    rec = RecorderProcess(config_path, logs)
    assert rec.detail["disk_policy"]["held_off_s"] == 0
    assert rec.stop() == 0
    assert f"{STATE_FILE} unreadable" in rec.stderr
    pubsub.unlink_all(load_config(config_path))
