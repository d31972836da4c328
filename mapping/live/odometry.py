"""The live worker's distance along the drive, integrated from the wheel speeds (what its windows are placed by)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

KNOT_NS = 500_000_000


@dataclass
class Odometry:
    """Distance along the drive at host times, integrated from the wheel speeds message by message.

    It depends only on the messages, never on when the worker looks at them, so the windows' time
    ranges are the same in every replay of a log (a distance read off successive pose fusions depended
    on how much data each fusion happened to have). Knots at least `KNOT_NS` apart, the newest message
    always the last knot; the integration state is kept so a restart goes on where the journal left off."""

    knots_t: list[int] = field(default_factory=list)
    knots_s: list[float] = field(default_factory=list)
    last_speed_mps: float = 0.0

    def add(self, host_ns: int, speed_mps: float) -> bool:
        """Integrate one wheel-speed message (trapezoids); False for one not after the last."""
        if not self.knots_t:
            self.knots_t, self.knots_s, self.last_speed_mps = [host_ns], [0.0], speed_mps
            return True
        last_t = self.knots_t[-1]
        if host_ns <= last_t:
            return False
        s = self.knots_s[-1] + 0.5 * (speed_mps + self.last_speed_mps) * (host_ns - last_t) / 1e9
        if len(self.knots_t) >= 2 and last_t - self.knots_t[-2] < KNOT_NS:
            self.knots_t[-1], self.knots_s[-1] = host_ns, s  # the tip moves on
        else:
            self.knots_t.append(host_ns)
            self.knots_s.append(s)
        self.last_speed_mps = speed_mps
        return True

    def distance_after(self, later: list[tuple[int, float]]) -> float:
        """The distance once the `later` (host ns, speed) messages are integrated, without adding them: what the
        health reports while a window is fitted and the messages wait for the next `add`."""
        tip = Odometry(self.knots_t[-1:], self.knots_s[-1:], self.last_speed_mps)  # `add` on a copy of the tip
        for host_ns, speed in later:
            tip.add(host_ns, speed)
        return tip.distance_m

    @property
    def distance_m(self) -> float:
        return self.knots_s[-1] if self.knots_s else 0.0

    def time_at(self, s: float) -> int:
        """First host time at which the drive reached distance s (clamped to the known span)."""
        arr = np.asarray(self.knots_s)
        i = int(np.searchsorted(arr, s, side="left"))
        if i <= 0:
            return self.knots_t[0]
        if i >= len(arr):
            return self.knots_t[-1]
        span = arr[i] - arr[i - 1]
        f = 0.0 if span <= 0 else (s - arr[i - 1]) / span
        return int(self.knots_t[i - 1] + f * (self.knots_t[i] - self.knots_t[i - 1]))


def wheel_speed_mps(msg: object) -> float | None:
    """The vehicle's speed from one WheelSpeeds message: the mean of the wheels that report one."""
    speeds = [abs(v) for v in (msg.front_left_mps, msg.front_right_mps, msg.rear_left_mps, msg.rear_right_mps)
              if np.isfinite(v)]
    return float(np.mean(speeds)) if speeds else None
