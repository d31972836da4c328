"""`python -m drivers.can.can_driver`: the real process, fed over udp_multicast, read back from the bus."""

from __future__ import annotations

import random
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import pytest
import yaml

from daemon.bus import pubsub
from daemon.spine.config import load_config
from daemon.spine.topics import CAN_FRAMES, WHEEL_SPEEDS, health_topic
from drivers.can.wheel_speed_codec import encode_wheel_speeds, load_dbc

ROOT = Path(__file__).resolve().parents[2]
pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack (python-can[multicast])")


def write_config(tmp_path: Path, group: str) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"]["shm_prefix"] = f"t{uuid.uuid4().hex[:12]}"
    data["sensors"]["can"]["channel"] = group
    shutil.copy(ROOT / "configs" / "sim_car.dbc", tmp_path / "sim_car.dbc")  # relative to the config's folder
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_can_driver_process_publishes_wheel_speeds_frames_and_health(tmp_path):
    group = f"239.75.{random.randrange(256)}.{random.randrange(1, 255)}"
    config_path = write_config(tmp_path, group)
    car = load_config(config_path)
    proc = subprocess.Popen([sys.executable, "-m", "drivers.can.can_driver", "--config", str(config_path)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        health = pubsub.open_subscriber(car, health_topic("can"), start="oldest", wait_s=20)
        speeds = pubsub.open_subscriber(car, WHEEL_SPEEDS, start="oldest", wait_s=5)
        frames = pubsub.open_subscriber(car, CAN_FRAMES, start="oldest", wait_s=5)
        assert health.read(timeout_s=10) is not None  # the driver is up and listening
        db = load_dbc(ROOT / "configs" / "sim_car.dbc")
        sender = can.Bus(interface="udp_multicast", channel=group)
        n = 60
        for i in range(n):
            v = 3.0 + 0.25 * i
            for frame in encode_wheel_speeds(db, car.sensors.can.signals, v, v, v + 0.01, v + 0.01, 0.05, counter=i):
                sender.send(frame)
            time.sleep(0.002)
        sender.shutdown()
        got = []
        deadline = time.monotonic() + 10
        while len(got) < n and time.monotonic() < deadline:
            msg = speeds.read(timeout_s=0.2, copy=True)
            if msg is not None and msg.yaw_rate_rps == pytest.approx(0.05, abs=1e-4):  # ours, not a neighbour's
                got.append(msg)
        assert [round(m.front_left_mps, 2) for m in got] == [round(3.0 + 0.25 * i, 2) for i in range(n)]
        assert [m.seq for m in got] == list(range(got[0].seq, got[0].seq + n))
        assert all(m.host_mono_ns > 0 for m in got)
        raw = []
        while (msg := frames.read(timeout_s=0.5, copy=True)) is not None:
            raw.append(msg)
        assert sum(m.arbitration_id == 0xAA for m in raw) >= n and sum(m.arbitration_id == 0x24 for m in raw) >= n
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert "can driver stopped" in out and "wheel_speeds=" in out
        last = None
        while (msg := health.read(timeout_s=0.2)) is not None:
            last = msg
        assert last is not None and last.process == "can" and last.received >= 2 * n
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        pubsub.unlink_all(car)
