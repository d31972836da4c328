"""bench/memory.py's synthetic drive is self-consistent: GNSS, IMU and wheel speeds describe one motion,
which the pose fusion recovers; camera frames and masks come in pairs at the camera rate."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

from daemon.spine.config import CarConfig
from daemon.spine.health import process_memory_mb
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import CameraFrame, GnssFix, ImuSample, SemanticMask, WheelSpeeds
from daemon.spine.topics import GNSS_FIX, IMU, WHEEL_SPEEDS, camera_topic, mask_topic
from mapping.inputs.drive_inputs import fuse_log_trajectory
from mapping.localization.sensor_time import ClockMap

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def memory_bench():
    spec = importlib.util.spec_from_file_location("memory_bench", REPO / "bench" / "memory.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def config(memory_bench):
    return CarConfig.model_validate(memory_bench.car_config_data())


@pytest.fixture(scope="module")
def drive(memory_bench, config):
    pairs = [(CameraFrame(camera=memory_bench.CAMERA, format="jpeg", data=bytes([i])),
              SemanticMask(camera=memory_bench.CAMERA, format="png", data=bytes([i]))) for i in range(3)]
    by_topic: dict[str, list] = {}
    order = []
    for topic, msg in memory_bench.drive_messages(0.3, pairs, 5_000_000_000, config):
        by_topic.setdefault(topic, []).append(msg)
        order.append(msg.host_mono_ns)
    return by_topic, order


def test_messages_in_time_order_at_the_sensor_rates(memory_bench, drive):
    by_topic, order = drive
    assert np.all(np.diff(order) >= 0)
    seconds = 300.0 / memory_bench.SPEED
    for topic, kind in ((GNSS_FIX, "gnss"), (IMU, "imu"), (WHEEL_SPEEDS, "wheels"),
                        (camera_topic(memory_bench.CAMERA), "camera"), (mask_topic(memory_bench.CAMERA), "camera")):
        assert len(by_topic[topic]) == int(seconds * memory_bench.RATES_HZ[kind]) + 1, topic
    frames, masks = by_topic[camera_topic(memory_bench.CAMERA)], by_topic[mask_topic(memory_bench.CAMERA)]
    assert [f.sensor_time_ns for f in frames] == [m.sensor_time_ns for m in masks]
    assert [f.data for f in frames[:4]] == [bytes([0]), bytes([1]), bytes([2]), bytes([0])]  # cyclic
    assert [f.data for f in frames] == [m.data for m in masks]  # each frame with its own mask


def test_gnss_wheels_and_imu_describe_one_motion(memory_bench, drive, config):
    by_topic, _ = drive
    fixes: list[GnssFix] = by_topic[GNSS_FIX]
    enu = LocalFrame(*memory_bench.ORIGIN).geodetic_to_enu(np.array([f.latitude_deg for f in fixes]),
                                                            np.array([f.longitude_deg for f in fixes]),
                                                            np.array([f.altitude_m for f in fixes]))
    t = np.array([f.sensor_time_ns for f in fixes]) - fixes[0].sensor_time_ns
    lever = config.sensors.gnss.antenna_lever_arm_m
    assert np.abs(enu - memory_bench.antenna_enu(t / 1e9, lever)).max() < 0.15  # 2 cm noise
    radius = np.hypot(enu[:, 0], enu[:, 1] - memory_bench.RADIUS)  # the antenna 0.5 m ahead: a wider circle
    assert np.abs(radius - np.hypot(memory_bench.RADIUS, lever[0])).max() < 0.15
    truth = memory_bench.vehicle_enu(t / 1e9)
    gnss_path_m = np.linalg.norm(np.diff(truth, axis=0), axis=1).sum()

    wheels: list[WheelSpeeds] = by_topic[WHEEL_SPEEDS]
    wt = np.array([w.sensor_time_ns for w in wheels]) / 1e9
    rear = np.array([(w.rear_left_mps + w.rear_right_mps) / 2 for w in wheels])
    wheel_path_m = float(np.sum(0.5 * (rear[1:] + rear[:-1]) * np.diff(wt)))
    assert wheel_path_m == pytest.approx(gnss_path_m, rel=1e-3)
    # the outer wheels turn faster by the yaw rate times the track; the yaw rate is the GNSS heading's rate
    diff = np.array([(w.rear_right_mps - w.rear_left_mps) / config.vehicle.track_width_m for w in wheels])
    heading = np.unwrap(np.arctan2(np.diff(truth[:, 1]), np.diff(truth[:, 0])))
    heading_rate = (heading[-1] - heading[0]) / ((t[-2] - t[0]) / 1e9)
    for value in (diff, np.array([w.yaw_rate_rps for w in wheels])):
        assert value == pytest.approx(heading_rate, rel=1e-6)

    imu: list[ImuSample] = by_topic[IMU]
    assert all(s.gyro_rps[2] == pytest.approx(heading_rate, rel=1e-6) for s in imu)
    # specific force in the vehicle frame (x forward, y left, z up): centripetal to the left, gravity up
    assert all(s.accel_mps2[1] == pytest.approx(memory_bench.SPEED**2 / memory_bench.RADIUS) for s in imu)
    assert all(s.accel_mps2[2] == pytest.approx(memory_bench.G) for s in imu)


def test_pose_fusion_follows_the_synthetic_drive(memory_bench, drive, config):
    """What the worker fuses from the feed is the circle the bench drives (so its windows are where the
    bench thinks they are)."""
    by_topic, _ = drive
    clocks = {t: ClockMap("host") for t in (GNSS_FIX, IMU, WHEEL_SPEEDS)}
    origin = LocalFrame(*memory_bench.ORIGIN)
    traj = fuse_log_trajectory(by_topic[GNSS_FIX], by_topic[IMU], by_topic[WHEEL_SPEEDS], config, origin, clocks)
    t = (traj.times_ns - 5_000_000_000) / 1e9
    err = np.linalg.norm(traj.positions - memory_bench.vehicle_enu(t), axis=1)
    assert np.max(err) < 0.1  # the antenna's lever arm (0.5 m) taken off, 2 cm GNSS noise
    length = float(traj.distance_3d_at(traj.times_ns[-1:])[0])
    assert length == pytest.approx(memory_bench.SPEED * (t[-1] - t[0]), rel=1e-3)


def test_rss_slope_over_the_drive_second_half(memory_bench):
    samples = [(m, 500.0 + 0.01 * m) for m in np.arange(0, 1000, 10.0)] + [(1000.0, 400.0)]
    assert memory_bench.rss_slope_mb_per_km(samples[:-1], 500.0) == pytest.approx(10.0)
    assert memory_bench.rss_slope_mb_per_km([(0.0, 1.0)] * 10, 0.0) is None  # no distance covered


def test_process_memory_reads_this_process():
    for pid in (os.getpid(), "self"):
        status = process_memory_mb(pid)
        assert 0 < status["VmRSS"] <= status["VmHWM"]
