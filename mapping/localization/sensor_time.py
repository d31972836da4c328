"""Putting every sensor's own timestamps on the host monotonic clock.

A topic's sensor clock is recognised from its stamps:
- host-synchronised (stamps within a second of their host arrival times, e.g. OAK cameras): kept as they are;
- UTC / PTP (stamps within an hour of the wall-clock time of their arrival, e.g. GNSS epochs, a PTP Lidar,
  CAN receive times): mapped through the log's monotonic/UTC time anchors, so transport latency does
  not bias them;
- free-running (anything else, e.g. an IMU counting ticks since power-on): a straight line host = a * stamp + b
  fitted to the arrivals (drift included), shifted down to the earliest arrival: the offset then carries
  only the shortest transport latency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemon.spine.messages import HOST_CLOCK_WITHIN_NS

UTC_WITHIN_NS = 3600 * 1_000_000_000


@dataclass(frozen=True)
class ClockMap:
    kind: str  # "host" | "utc" | "free"
    scale: float = 1.0  # free: host ns per stamp ns
    offset_ns: float = 0.0  # free: host time of first_stamp_ns
    first_stamp_ns: int = 0
    anchor_mono_ns: np.ndarray | None = None  # utc: anchor times and (utc - mono) at them
    anchor_utc_minus_mono_ns: np.ndarray | None = None

    def to_host(self, stamps_ns: np.ndarray) -> np.ndarray:
        stamps = np.asarray(stamps_ns, np.int64)
        if self.kind == "host":
            return stamps
        if self.kind == "utc":
            # mono = utc - (utc - mono), the difference interpolated between anchors (it drifts slowly),
            # relative to the first anchor: UTC nanoseconds (~1.7e18) hold in a float64 only to 256 ns, and
            # absolute values would round every stamp differently for each offset between the log's and
            # this host's monotonic clocks (a replay's trajectory would move with the moment it is played)
            mono0, diff0 = int(self.anchor_mono_ns[0]), int(self.anchor_utc_minus_mono_ns[0])
            approx_mono = (stamps - diff0 - mono0).astype(np.float64)
            diff = np.interp(approx_mono, (self.anchor_mono_ns - mono0).astype(np.float64),
                             (self.anchor_utc_minus_mono_ns - diff0).astype(np.float64))
            return stamps - diff0 - np.rint(diff).astype(np.int64)
        rel = (stamps - self.first_stamp_ns).astype(np.float64)
        return np.rint(self.offset_ns + self.scale * rel).astype(np.int64)


def fit_clock(stamps_ns: np.ndarray, host_ns: np.ndarray, anchors: list[tuple[int, int]]) -> ClockMap:
    """The map of one topic's stamps onto the host clock, from (stamp, host arrival) pairs and (mono, utc) anchors."""
    stamps = np.asarray(stamps_ns, np.int64)
    host = np.asarray(host_ns, np.int64)
    if len(stamps) == 0 or np.median(np.abs(host - stamps)) < HOST_CLOCK_WITHIN_NS:
        return ClockMap("host")
    if anchors:
        mono = np.array([a[0] for a in anchors], np.int64)
        order = np.argsort(mono)
        mono = mono[order]
        utc_minus_mono = np.array([a[1] - a[0] for a in anchors], np.int64)[order]
        if np.median(np.abs(stamps - (host + utc_minus_mono[0]))) < UTC_WITHIN_NS:
            return ClockMap("utc", anchor_mono_ns=mono, anchor_utc_minus_mono_ns=utc_minus_mono)
    rel = (stamps - stamps[0]).astype(np.float64)
    arrivals = (host - host[0]).astype(np.float64)
    scale = float(np.polyfit(rel, arrivals, 1)[0]) if len(stamps) > 1 and np.ptp(rel) > 0 else 1.0
    offset = float(np.min(arrivals - scale * rel)) + float(host[0])
    return ClockMap("free", scale, offset, int(stamps[0]))


def fit_clocks(messages_by_topic: dict[str, list], anchors: list[tuple[int, int]]) -> dict[str, ClockMap]:
    """`fit_clock` for each topic that has messages, from the messages' own sensor_time_ns and host_mono_ns."""
    return {topic: fit_clock([m.sensor_time_ns for m in messages], [m.host_mono_ns for m in messages], anchors)
            for topic, messages in messages_by_topic.items() if messages}


FREE_CLOCK_RATE_FIT_MIN_S = 600.0  # shorter spans: a free-running clock is taken at rate 1


def span_clock(stamps_ns: list[int], host_ns: list[int], anchors: list[tuple[int, int]]) -> ClockMap:
    """`fit_clock` for the few seconds or minutes the worker holds, in exact arithmetic where it matters.

    Over a short span the fitted rate of a free-running clock is arrival jitter, not drift (a crystal
    drifts < 100 ppm: 6 ms a minute), and a rate error stretches that sensor's time axis, so wheel
    speeds integrate to a wrong distance. The offset is refitted with rate 1 (shortest latency), in
    integers."""
    clock = fit_clock(stamps_ns, host_ns, anchors)
    if clock.kind != "free" or len(stamps_ns) == 0:
        return clock
    stamps, host = np.asarray(stamps_ns, np.int64), np.asarray(host_ns, np.int64)
    if (stamps.max() - stamps.min()) > FREE_CLOCK_RATE_FIT_MIN_S * 1e9:
        return clock
    offset = float(np.min(host - host[0] - (stamps - stamps[0]))) + float(host[0])
    return ClockMap("free", 1.0, offset, int(stamps[0]))
