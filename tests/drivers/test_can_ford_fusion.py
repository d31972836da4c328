"""Real Ford Fusion candump logs played (as fast as possible) through the CAN driver on a virtual bus.

The opendbc Ford DBC gives wheel speeds as wheel angular rate (rad/s): the config says so (`speed_unit: rad/s`)
with the car's rolling radius (235/45R18 tyres), and the driver publishes road speed.
"""

from __future__ import annotations

from pathlib import Path

import can
import cantools
import numpy as np
import pytest

from daemon.spine.config import CanConfig, CanSignals
from daemon.spine.topics import CAN_FRAMES, WHEEL_SPEEDS
from tests.drivers.can_driver_thread import can_driver_thread

DATA = Path("/work/shared/data/can_ford_fusion")
DBC = DATA / "ford_fusion_2018_pt.dbc"
ROLLING_RADIUS_M = 0.345
pytestmark = pytest.mark.skipif(not DBC.exists(), reason="shared Ford Fusion data not present")

FORD_SIGNALS = CanSignals(
    wheel_speed_fl="WheelSpeed_CG1.WhlFl_W_Meas",
    wheel_speed_fr="WheelSpeed_CG1.WhlFr_W_Meas",
    wheel_speed_rl="WheelSpeed_CG1.WhlRl_W_Meas",
    wheel_speed_rr="WheelSpeed_CG1.WhlRr_W_Meas",
    yaw_rate="Yaw_Data.VehYaw_W_Actl",
    speed_unit="rad/s",
    wheel_radius_m=ROLLING_RADIUS_M,
    yaw_rate_unit="rad/s",
)


def play_log(log: Path, channel: str, inject_error_every: int = 0):
    """Replay a candump log onto a virtual bus through the driver; return (published, stats, health, sent)."""
    config = CanConfig(interface="virtual", channel=channel, bitrate=None, dbc_file=str(DBC), signals=FORD_SIGNALS)
    with can_driver_thread(config, DBC) as driver:
        sender = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        sent = 0
        for i, msg in enumerate(can.MessageSync(can.CanutilsLogReader(log), timestamps=False, gap=0.0)):
            if inject_error_every and i % inject_error_every == 0:
                error_class = 0x80 if (i // inject_error_every) % 2 else 0x40  # bus error, bus-off
                sender.send(can.Message(timestamp=msg.timestamp, is_error_frame=True, arbitration_id=error_class,
                                        data=bytes([0, 0, 0x08, 0x19, 0, 0, 0, 0])))
                sent += 1
            sender.send(msg)
            sent += 1
        while driver.count(CAN_FRAMES) < sent and driver.thread.is_alive():
            driver.stop.wait(0.01)
    sender.shutdown()
    return driver.published, driver.stats, driver.health, sent


def road_speed_kmh(published) -> tuple[np.ndarray, np.ndarray]:
    speeds = [m for t, m in published if t == WHEEL_SPEEDS]
    t = np.array([s.sensor_time_ns for s in speeds]) / 1e9
    w = np.array([[s.front_left_mps, s.front_right_mps, s.rear_left_mps, s.rear_right_mps] for s in speeds])
    return t - t[0], w * 3.6


def latest_yaw_per_wheel_frame(log: Path) -> np.ndarray:
    """Straight from the log with cantools: the yaw of the last 0x091 before each 0x217 (NaN before any).

    On these 2017 logs the 2018 DBC's VehYaw_W_Actl spreads over its whole range (not a yaw rate on this
    car), so the check is the pairing, not the physics.
    """
    db = cantools.database.load_file(str(DBC), strict=False)
    yaw, out = np.nan, []
    for m in can.CanutilsLogReader(log):
        if m.arbitration_id == 0x091:
            yaw = db.decode_message(0x091, m.data)["VehYaw_W_Actl"]
        elif m.arbitration_id == 0x217:
            out.append(yaw)
    return np.array(out)


def wheel_frames_in(log: Path) -> int:
    return sum(1 for m in can.CanutilsLogReader(log) if m.arbitration_id == 0x217)


@pytest.mark.parametrize(("name", "start_kmh", "end_kmh"), [
    ("acc_on_speed_changing_from_30km_to_80km_per_hour", 30, 80),
    ("acc_on_speed_changing_from_80km_to_30km_per_hour", 80, 30),
    ("acc_on_going_at_50km_per_hour", 50, 50),
])
def test_wheel_speeds_follow_the_recorded_drive(name, start_kmh, end_kmh):
    log = DATA / f"{name}.candump"
    published, stats, health, sent = play_log(log, f"ford_{start_kmh}_{end_kmh}")
    t, kmh = road_speed_kmh(published)
    assert stats.frames == sent == sum(1 for _ in can.CanutilsLogReader(log))
    assert stats.wheel_speeds == len(t) == wheel_frames_in(log)
    assert stats.undecodable == 0 and stats.error_frames == 0
    assert 1.0 / np.median(np.diff(t)) == pytest.approx(100, rel=0.1)  # ~100 Hz
    first, last = kmh[t < 0.5].mean(), kmh[t > t[-1] - 0.5].mean()
    assert first == pytest.approx(start_kmh, abs=3)
    assert last == pytest.approx(end_kmh, abs=3)
    assert np.abs(kmh - kmh.mean(axis=1, keepdims=True)).max() < 1.5  # four wheels agree (driving straight)
    if start_kmh != end_kmh:  # the change is monotone once smoothed over 1 s
        per_second = [kmh[(t >= s) & (t < s + 1)].mean() for s in range(int(t[-1]))]
        steps = np.diff(per_second) * np.sign(end_kmh - start_kmh)
        assert steps.min() > -0.5
    yaw = np.array([m.yaw_rate_rps for tp, m in published if tp == WHEEL_SPEEDS])
    np.testing.assert_allclose(yaw, latest_yaw_per_wheel_frame(log), atol=1e-9)
    assert health.errors == 0


def test_injected_error_frames_are_counted_and_the_drive_still_decodes():
    log = DATA / "acc_on_going_at_50km_per_hour.candump"
    published, stats, health, sent = play_log(log, "ford_errors", inject_error_every=100)
    n_log = sum(1 for _ in can.CanutilsLogReader(log))
    injected = sent - n_log
    assert injected == len(range(0, n_log, 100))
    assert stats.error_frames == injected and stats.bus_off == (injected + 1) // 2
    assert health.errors == injected
    flagged = [m for t, m in published if t == CAN_FRAMES and m.is_error_frame]
    assert len(flagged) == injected
    assert stats.wheel_speeds == wheel_frames_in(log)
    _, kmh = road_speed_kmh(published)
    assert kmh.mean() == pytest.approx(50, abs=2)
