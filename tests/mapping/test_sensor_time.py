"""Sensor clocks onto the host clock: host-synced kept, UTC through the anchors, free-running fitted."""

import numpy as np

from mapping.localization.sensor_time import fit_clock

MONO0 = 3_600_000_000_000
UTC0 = 1_780_000_000_000_000_000


def _arrivals(true_ns, latency_ns, rng):
    return MONO0 + true_ns + latency_ns + rng.exponential(2e6, true_ns.shape).astype(np.int64)


def test_three_kinds_of_clock():
    rng = np.random.default_rng(0)
    true = np.arange(0, 60_000_000_000, 10_000_000, dtype=np.int64)
    anchors = [(MONO0 + k * 1_000_000_000, UTC0 + k * 1_000_000_000 + k * 1000) for k in range(61)]  # UTC drifts
    host = _arrivals(true, 30_000_000, rng)
    synced = fit_clock(MONO0 + true + 200_000, host, anchors)
    assert synced.kind == "host"
    utc_stamps = UTC0 + true + (true // 1_000_000_000) * 1000
    utc = fit_clock(utc_stamps, _arrivals(true, 45_000_000, rng), anchors)
    assert utc.kind == "utc"
    assert np.abs(utc.to_host(utc_stamps) - (MONO0 + true)).max() < 2000  # latency does not bias it
    ticks = 123_456_789 + (true * (1 + 25e-6)).astype(np.int64)  # free-running, 25 ppm fast
    free = fit_clock(ticks, _arrivals(true, 12_000_000, rng), anchors)
    assert free.kind == "free"
    err = free.to_host(ticks) - (MONO0 + true)
    assert abs(err.mean() - 12_000_000) < 1_000_000  # only the shortest latency remains
    assert np.ptp(err) < 200_000  # the drift is fitted out
