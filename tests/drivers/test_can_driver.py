"""The CAN driver on python-can's in-process virtual bus: frames, wheel speeds, error frames, bus errors."""

from __future__ import annotations

import itertools
import math
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from daemon.spine.config import CanConfig, load_config
from daemon.spine.health import HealthCounters
from daemon.spine.messages import CanFrame, DriverHealth, WheelSpeeds
from daemon.spine.topics import CAN_FRAMES, WHEEL_SPEEDS, health_topic
from drivers.can.can_bus import open_can_bus
from drivers.can.can_driver import run_can_driver
from drivers.can.wheel_speed_codec import encode_wheel_speeds, load_dbc

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
SIM_DBC = CONFIGS / "sim_car.dbc"
_channels = itertools.count()


def virtual_config(**update) -> CanConfig:
    sim = load_config(CONFIGS / "sim.yaml").sensors.can
    return sim.model_copy(update={"interface": "virtual", "channel": f"test_can_{next(_channels)}",
                                  "bitrate": None, **update})


class DriverThread:
    """run_can_driver in a thread, publishing into a list; `opened` is set each time it opens its bus."""

    def __init__(self, config: CanConfig, open_bus=open_can_bus, **kwargs):
        self.published: list[tuple[str, object]] = []
        self.stop = threading.Event()
        self.opened = threading.Event()
        self.health = HealthCounters("can")
        self.stats = None

        def opening(cfg, **kw):
            bus = open_bus(cfg, **kw)
            self.opened.set()
            return bus

        def target():
            self.stats = run_can_driver(config, SIM_DBC, lambda t, m: self.published.append((t, m)), self.stop,
                                        self.health, open_bus=opening, **kwargs)

        self.thread = threading.Thread(target=target, daemon=True)
        self.thread.start()
        assert self.opened.wait(5.0)

    def of(self, topic: str) -> list:
        return [m for t, m in self.published if t == topic]

    def wait_for(self, topic: str, n: int, timeout_s: float = 10.0) -> list:
        deadline = time.monotonic() + timeout_s
        while len(self.of(topic)) < n and time.monotonic() < deadline:
            time.sleep(0.005)
        return self.of(topic)

    def finish(self):
        self.stop.set()
        self.thread.join(5.0)
        assert not self.thread.is_alive()
        return self.stats


def test_wheel_speeds_and_raw_frames_on_a_virtual_bus():
    config = virtual_config()
    db = load_dbc(SIM_DBC)
    driver = DriverThread(config)
    sender = can.Bus(interface="virtual", channel=config.channel, preserve_timestamps=True)
    t0 = 1_700_000_000.0
    sent = []
    for i in range(50):
        speed = 5.0 + 0.1 * i
        frames = encode_wheel_speeds(db, config.signals, speed, speed + 0.02, speed - 0.02, speed + 0.04,
                                     0.01 * i, counter=i)
        for k, f in enumerate(frames):
            f.timestamp = t0 + 0.02 * i + 0.001 * k
            sender.send(f)
            sent.append(f)
    sender.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", timestamp=t0 + 2.0))
    speeds = driver.wait_for(WHEEL_SPEEDS, 50)
    frames = driver.wait_for(CAN_FRAMES, 101)
    stats = driver.finish()
    sender.shutdown()

    assert len(speeds) == 50 and len(frames) == 101
    assert all(isinstance(m, WheelSpeeds) for m in speeds)
    for i, ws in enumerate(speeds):
        speed = 5.0 + 0.1 * i
        # 0.01 km/h steps: within half a step
        assert ws.front_left_mps == pytest.approx(speed, abs=0.0015)
        assert ws.front_right_mps == pytest.approx(speed + 0.02, abs=0.0015)
        assert ws.rear_left_mps == pytest.approx(speed - 0.02, abs=0.0015)
        assert ws.rear_right_mps == pytest.approx(speed + 0.04, abs=0.0015)
        # 0.01 deg/s steps
        assert ws.yaw_rate_rps == pytest.approx(0.01 * i, abs=1e-4)
        assert ws.sensor_time_ns == round((t0 + 0.02 * i + 0.001) * 1e9)
    assert [(f.arbitration_id, f.data) for f in frames] == [(m.arbitration_id, bytes(m.data)) for m in sent] + [
        (0x123, b"\x01\x02")]
    assert frames[-1].channel == config.channel
    assert all(isinstance(f, CanFrame) and not f.is_error_frame for f in frames)
    assert stats.frames == 101 and stats.wheel_speeds == 50 and stats.undecodable == 0
    assert driver.health.received == 101 and driver.health.published == 151
    assert driver.health.sequence_gaps == 0


def test_yaw_rate_is_nan_without_a_yaw_signal_or_before_the_first_yaw_frame():
    signals = virtual_config().signals.model_copy(update={"yaw_rate": None})
    config = virtual_config(signals=signals)
    db = load_dbc(SIM_DBC)
    driver = DriverThread(config)
    sender = can.Bus(interface="virtual", channel=config.channel)
    frames = encode_wheel_speeds(db, signals, 1.0, 1.0, 1.0, 1.0, 0.3)
    assert len(frames) == 1  # no yaw frame without a yaw signal
    sender.send(frames[0])
    # a yaw frame on the bus is not used when the config names no yaw signal
    sender.send(encode_wheel_speeds(db, virtual_config().signals, 1.0, 1.0, 1.0, 1.0, 0.3)[0])
    sender.send(frames[0])
    speeds = driver.wait_for(WHEEL_SPEEDS, 2)
    driver.finish()
    sender.shutdown()
    assert len(speeds) == 2 and all(math.isnan(s.yaw_rate_rps) for s in speeds)


def test_error_frames_and_undecodable_frames_are_counted_not_fatal():
    config = virtual_config()
    db = load_dbc(SIM_DBC)
    driver = DriverThread(config)
    sender = can.Bus(interface="virtual", channel=config.channel)
    good = encode_wheel_speeds(db, config.signals, 3.0, 3.0, 3.0, 3.0, 0.0, counter=0)
    sender.send(can.Message(is_error_frame=True, arbitration_id=0x4, data=bytes([0, 0x10, 0, 0, 0, 0, 0, 0])))
    sender.send(can.Message(is_error_frame=True, arbitration_id=0x40, data=bytes(8)))  # bus-off
    sender.send(can.Message(arbitration_id=0xAA, is_extended_id=False, data=b"\x00\x01\x02"))  # short wheel-speed frame
    bad_checksum = bytearray(good[0].data)
    bad_checksum[-1] ^= 0xFF
    sender.send(can.Message(arbitration_id=0x24, is_extended_id=False, data=bad_checksum))
    sender.send(can.Message(arbitration_id=0xAA, is_extended_id=False, is_remote_frame=True, dlc=8))
    for f in good:
        sender.send(f)
    for f in encode_wheel_speeds(db, config.signals, 3.0, 3.0, 3.0, 3.0, 0.0, counter=5):  # 4 yaw frames lost
        sender.send(f)
    speeds = driver.wait_for(WHEEL_SPEEDS, 2)
    frames = driver.wait_for(CAN_FRAMES, 9)
    stats = driver.finish()
    sender.shutdown()

    assert len(speeds) == 2 and speeds[0].front_left_mps == pytest.approx(3.0, abs=0.0015)
    assert [f.is_error_frame for f in frames] == [True, True] + [False] * 7
    assert frames[4].is_remote_frame
    assert stats.error_frames == 2 and stats.bus_off == 1 and stats.undecodable == 2
    assert driver.health.errors == 2 and driver.health.rejected == 2
    assert driver.health.sequence_gaps == 1
    health = [m for t, m in driver.published if t == health_topic("can")]
    assert isinstance(health[-1], DriverHealth) and "bus_off=1" in health[-1].detail
    assert health[-1].errors == 2 and health[-1].rejected == 2


class FailingBus:
    """Delegates to a real bus and raises CanOperationError on the given recv call."""

    def __init__(self, bus: can.BusABC, fail_on_recv: int):
        self.bus, self.calls, self.fail_on = bus, 0, fail_on_recv

    def recv(self, timeout=None):
        self.calls += 1
        if self.calls == self.fail_on:
            raise can.CanOperationError("Network is down [Error Code 100]")
        return self.bus.recv(timeout)

    def shutdown(self):
        self.bus.shutdown()


def test_bus_errors_reopen_the_bus_with_backoff():
    config = virtual_config()
    db = load_dbc(SIM_DBC)
    opens = []

    def flaky_open(cfg, **kw):
        opens.append(time.monotonic())
        if len(opens) in (2, 3):  # the first two reopen attempts fail: the adapter is gone
            raise can.CanInterfaceNotImplementedError("no such device")
        bus = open_can_bus(cfg, **kw)
        return FailingBus(bus, fail_on_recv=3) if len(opens) == 1 else bus

    driver = DriverThread(config, open_bus=flaky_open)
    sender = can.Bus(interface="virtual", channel=config.channel)
    deadline = time.monotonic() + 10
    while len(opens) < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)
    for f in encode_wheel_speeds(db, config.signals, 2.0, 2.0, 2.0, 2.0, 0.1):
        sender.send(f)
    speeds = driver.wait_for(WHEEL_SPEEDS, 1)
    stats = driver.finish()
    sender.shutdown()

    assert len(opens) == 4
    assert stats.reopens == 1 and stats.bus_errors == 3
    assert driver.health.errors == 3 and "no such device" in driver.health.last_error
    gaps = [b - a for a, b in itertools.pairwise(opens)]
    assert gaps[0] >= 0.04 and gaps[1] >= 0.09 and gaps[2] >= 0.19  # backoff 0.05, 0.1, 0.2 s
    assert gaps[2] > 1.5 * gaps[1]
    assert len(speeds) == 1 and speeds[0].yaw_rate_rps == pytest.approx(0.1, abs=1e-4)


def test_health_is_published_once_a_period():
    driver = DriverThread(virtual_config(), health_period_s=0.1)
    health = driver.wait_for(health_topic("can"), 6)
    driver.finish()
    assert len(health) >= 6 and all(h.process == "can" for h in health)
    gaps_s = np.diff([h.host_mono_ns for h in health]) / 1e9
    assert gaps_s.min() >= 0.099  # never more often than the period (a stalled loop does not catch up in a burst)
    assert np.median(gaps_s) < 0.35  # and about once a period: the loop wakes at least every recv timeout (0.1 s)


def test_a_stale_yaw_rate_is_not_paired_with_wheel_speeds():
    config = virtual_config()
    db = load_dbc(SIM_DBC)
    driver = DriverThread(config)
    sender = can.Bus(interface="virtual", channel=config.channel, preserve_timestamps=True)
    yaw, wheels = encode_wheel_speeds(db, config.signals, 4.0, 4.0, 4.0, 4.0, 0.2)
    for frame, t in ((yaw, 100.0), (wheels, 100.5), (wheels, 101.2)):  # the yaw is 1.2 s old at the last
        frame.timestamp = t
        sender.send(frame)
    speeds = driver.wait_for(WHEEL_SPEEDS, 2)
    driver.finish()
    sender.shutdown()
    assert speeds[0].yaw_rate_rps == pytest.approx(0.2, abs=1e-4) and math.isnan(speeds[1].yaw_rate_rps)
