"""Time as the simulated sensors and host see it: each sensor's own clock (offset, drift, stamp jitter) and
the host monotonic time at which each message arrives (latency plus a jittery tail).

True time is seconds from the start of the drive. The simulated host monotonic clock reads
HOST_MONO_AT_START_NS at true time 0 and the wall clock (UTC) reads the scenario's start_utc.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np

from daemon.spine.config import CarConfig
from sim.world.scenarios import Scenario

HOST_MONO_AT_START_NS = 3_600_000_000_000  # the host booted an hour before the drive
ESF_TICK_NS = 39_062.5  # u-blox ESF-RAW sensor time tag (drivers/gnss/gnss_messages.py)


@dataclass(frozen=True)
class SensorClock:
    """sensor stamp = base_ns + true_ns * (1 + drift_ppm * 1e-6) + N(0, stamp_jitter_ns);
    host arrival = HOST_MONO_AT_START_NS + true_ns + latency_ns + Exp(latency_jitter_ns)."""

    base_ns: int
    drift_ppm: float = 0.0
    stamp_jitter_ns: float = 0.0
    latency_ns: float = 0.0
    latency_jitter_ns: float = 0.0


def utc_start_ns(scenario: Scenario) -> int:
    when = dt.datetime.fromisoformat(scenario.start_utc.replace("Z", "+00:00"))
    return int(when.timestamp()) * 1_000_000_000 + when.microsecond * 1000


def sensor_stamp_ns(clock: SensorClock, true_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    true_ns = np.asarray(true_s, np.float64) * 1e9
    jitter = rng.normal(0.0, clock.stamp_jitter_ns, true_ns.shape) if clock.stamp_jitter_ns else 0.0
    return clock.base_ns + np.rint(true_ns * (1 + clock.drift_ppm * 1e-6) + jitter).astype(np.int64)


def host_arrival_ns(clock: SensorClock, true_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    true_ns = np.asarray(true_s, np.float64) * 1e9
    tail = rng.exponential(clock.latency_jitter_ns, true_ns.shape) if clock.latency_jitter_ns else 0.0
    return HOST_MONO_AT_START_NS + np.rint(true_ns + clock.latency_ns + tail).astype(np.int64)


def host_mono_ns(true_s: float) -> int:
    """The host monotonic clock at a true time (no latency)."""
    return HOST_MONO_AT_START_NS + round(true_s * 1e9)


def drive_clocks(config: CarConfig, scenario: Scenario, rng: np.random.Generator) -> dict[str, SensorClock]:
    """Clocks keyed "camera/<name>", "lidar", "gnss", "imu", "can".

    Cameras stamp on the host monotonic clock as a synchronised OAK does (sub-millisecond offset);
    the Lidar on PTP-disciplined UTC (tens of microseconds off); GNSS fixes are exact UTC epochs;
    the IMU counts ESF-RAW ticks since the receiver started; CAN frames carry the host's UTC receive time."""
    utc = utc_start_ns(scenario)
    clocks = {}
    for cam in config.sensors.cameras:
        clocks[f"camera/{cam.name}"] = SensorClock(
            base_ns=HOST_MONO_AT_START_NS + int(rng.uniform(-800_000, 800_000)), drift_ppm=rng.uniform(-20, 20),
            stamp_jitter_ns=60_000, latency_ns=35e6, latency_jitter_ns=6e6)
    clocks["lidar"] = SensorClock(base_ns=utc + int(rng.uniform(-50_000, 50_000)), drift_ppm=rng.uniform(-2, 2),
                                  stamp_jitter_ns=2_000, latency_ns=0.4e6, latency_jitter_ns=0.3e6)
    clocks["gnss"] = SensorClock(base_ns=utc, latency_ns=45e6, latency_jitter_ns=4e6)
    imu_start_ticks = int(rng.uniform(2e6, 4e6))
    clocks["imu"] = SensorClock(base_ns=int(imu_start_ticks * ESF_TICK_NS), drift_ppm=rng.uniform(-30, 30),
                                latency_ns=12e6, latency_jitter_ns=2e6)
    clocks["can"] = SensorClock(base_ns=utc + int(rng.uniform(-2e6, 2e6)), stamp_jitter_ns=20_000,
                                latency_ns=0.15e6, latency_jitter_ns=0.1e6)
    return clocks
