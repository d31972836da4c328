"""Hypothesis: random frames never raise out of the CAN driver; bad frames of the configured messages are counted.

Also the sim DBC's encode -> decode round trip over the whole signal range.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.spine.config import load_config
from daemon.spine.health import HealthCounters
from daemon.spine.topics import CAN_FRAMES, WHEEL_SPEEDS
from drivers.can.can_driver import run_can_driver
from drivers.can.wheel_speed_codec import (
    CanDecodeError,
    WheelSpeedDecoder,
    encode_wheel_speeds,
    load_dbc,
    wheel_speed_layout,
)
from tests.list_can_bus import ListBus

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
SIM_DBC = CONFIGS / "sim_car.dbc"
CONFIG = load_config(CONFIGS / "sim.yaml").sensors.can.model_copy(update={"interface": "virtual"})
WHEEL_ID, YAW_ID = 0xAA, 0x24


frame_ids = st.one_of(st.sampled_from([WHEEL_ID, YAW_ID]), st.integers(0, 0x7FF), st.integers(0, 0x1FFFFFFF))
frames = st.builds(
    lambda arb, ext, data, err, rtr: can.Message(
        arbitration_id=arb if ext else arb & 0x7FF, is_extended_id=ext, data=b"" if rtr else data,
        is_error_frame=err, is_remote_frame=rtr and not err, dlc=len(data), check=False, timestamp=1.0),
    frame_ids, st.booleans(), st.binary(max_size=8), st.booleans(), st.booleans(),
)


def expected_undecodable(msg: can.Message) -> bool:
    if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
        return False
    data = bytes(msg.data)
    if msg.arbitration_id == WHEEL_ID:
        return len(data) < 8
    if msg.arbitration_id == YAW_ID:
        if len(data) < 8:
            return True
        return data[7] != (YAW_ID + 8 + sum(data[:7])) & 0xFF
    return False


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(frames, max_size=40))
def test_random_frames_never_raise_and_bad_ones_are_counted(msgs):
    stop = threading.Event()
    published = []
    health = HealthCounters("can")
    stats = run_can_driver(CONFIG, SIM_DBC, lambda t, m: published.append((t, m)), stop, health,
                           open_bus=lambda cfg, **kw: ListBus(msgs, stop), health_period_s=3600)
    assert stats.frames == len(msgs) == sum(t == CAN_FRAMES for t, _ in published)
    assert stats.error_frames == sum(m.is_error_frame for m in msgs)
    assert stats.undecodable == sum(expected_undecodable(m) for m in msgs) == health.rejected
    good_wheels = [m for m in msgs if m.arbitration_id == WHEEL_ID and not m.is_extended_id
                   and not m.is_error_frame and not m.is_remote_frame and len(m.data) >= 8]
    speeds = [m for t, m in published if t == WHEEL_SPEEDS]
    assert stats.wheel_speeds == len(good_wheels) == len(speeds)
    assert all(math.isfinite(s.front_left_mps) and -18.8 < s.rear_right_mps < 163.3 for s in speeds)


def test_random_frames_through_the_ford_dbc():
    ford = Path("/work/shared/data/can_ford_fusion/ford_fusion_2018_pt.dbc")
    if not ford.exists():
        pytest.skip("shared Ford Fusion data not present")
    signals = CONFIG.signals.model_copy(update={
        "wheel_speed_fl": "WheelSpeed_CG1.WhlFl_W_Meas", "wheel_speed_fr": "WheelSpeed_CG1.WhlFr_W_Meas",
        "wheel_speed_rl": "WheelSpeed_CG1.WhlRl_W_Meas", "wheel_speed_rr": "WheelSpeed_CG1.WhlRr_W_Meas",
        "yaw_rate": "Yaw_Data.VehYaw_W_Actl", "speed_unit": "m/s", "yaw_rate_unit": "rad/s"})
    decoder = WheelSpeedDecoder(wheel_speed_layout(load_dbc(ford), signals))

    @settings(max_examples=300, deadline=None)
    @given(st.sampled_from([0x217, 0x091, 0x216]), st.binary(max_size=8))
    def check(arb, data):
        try:
            out = decoder.decode(arb, False, data, 0)
        except CanDecodeError:
            assert arb in (0x217, 0x091) and len(data) < 8
            return
        if arb == 0x217:
            assert 0 <= out.front_left_mps <= 0.04 * (2**14 - 1) + 1e-9
        else:
            assert out is None

    check()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-18.79, 163.2), min_size=4, max_size=4), st.floats(-5.71, 5.71),
       st.integers(0, 1000))
def test_sim_dbc_round_trip(speeds, yaw, counter):
    db = load_dbc(SIM_DBC)
    decoder = WheelSpeedDecoder(wheel_speed_layout(db, CONFIG.signals))
    out = None
    for frame in encode_wheel_speeds(db, CONFIG.signals, *speeds, yaw, counter=counter):
        out = decoder.decode(frame.arbitration_id, frame.is_extended_id, bytes(frame.data), 5) or out
    got = (out.front_left_mps, out.front_right_mps, out.rear_left_mps, out.rear_right_mps)
    assert got == pytest.approx(speeds, abs=0.005 / 3.6 + 1e-9)
    assert out.yaw_rate_rps == pytest.approx(yaw, abs=math.radians(0.005) + 1e-9)
