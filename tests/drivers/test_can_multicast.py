"""Across processes: a simulator-like process sends encoded wheel speeds over python-can's udp_multicast."""

from __future__ import annotations

import random
import subprocess
import sys
import time
from pathlib import Path

import pytest

from daemon.spine.config import load_config
from daemon.spine.topics import CAN_FRAMES, WHEEL_SPEEDS
from tests.drivers.can_driver_thread import can_driver_thread

ROOT = Path(__file__).resolve().parents[2]
pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack (python-can[multicast])")

SENDER = """
import sys, time, can
from daemon.spine.config import load_config
from drivers.can.wheel_speed_codec import encode_wheel_speeds, load_dbc
group, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
signals = load_config("configs/sim.yaml").sensors.can.signals
db = load_dbc("configs/sim_car.dbc")
bus = can.Bus(interface="udp_multicast", channel=group, port=port)
for i in range(n):
    v = 0.1 * i
    for frame in encode_wheel_speeds(db, signals, v, v + 0.5, v + 1.0, v + 1.5, -0.001 * i, counter=i):
        bus.send(frame)
    time.sleep(0.002)
bus.shutdown()
"""


def test_wheel_speeds_from_another_process_over_udp_multicast():
    config = load_config(ROOT / "configs" / "sim.yaml").sensors.can
    assert config.interface == "udp_multicast"
    group = f"239.74.{random.randrange(256)}.{random.randrange(1, 255)}"
    port = random.randrange(40000, 60000)  # udp_multicast binds the port on every address: keep tests apart
    config = config.model_copy(update={"channel": group})
    with can_driver_thread(config, ROOT / "configs" / config.dbc_file, join_s=5.0,
                           bus_kwargs={"port": port}) as driver:
        n = 200
        sender = subprocess.run([sys.executable, "-c", SENDER, group, str(port), str(n)], cwd=ROOT, timeout=60,
                                capture_output=True, text=True)
        assert sender.returncode == 0, sender.stderr
        deadline = time.monotonic() + 5
        while driver.count(WHEEL_SPEEDS) < n and time.monotonic() < deadline:
            time.sleep(0.01)
    published, health = driver.published, driver.health
    speeds = [m for t, m in published if t == WHEEL_SPEEDS]
    assert len(speeds) == n and sum(t == CAN_FRAMES for t, _ in published) == 2 * n
    for i, s in enumerate(speeds):
        v = 0.1 * i
        assert (s.front_left_mps, s.front_right_mps, s.rear_left_mps, s.rear_right_mps) == pytest.approx(
            (v, v + 0.5, v + 1.0, v + 1.5), abs=0.0015)
        assert s.yaw_rate_rps == pytest.approx(-0.001 * i, abs=1e-4)
    assert driver.stats.undecodable == 0 and health.sequence_gaps == 0
    stamps = [s.sensor_time_ns for s in speeds]
    assert stamps == sorted(stamps) and abs(stamps[-1] / 1e9 - time.time()) < 30  # receive time, wall clock
