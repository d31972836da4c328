"""The live worker's policy when it cannot keep up with the car, and at its stop. Pure functions of distances and
times (`mapper.lag`, docs/operations.md):

- behind: when the next window ended more than `max_behind_m` behind the car, the worker skips to the newest
  window that has ended; the windows between are journalled `skipped` (their span, host times and log segments:
  `roadlog reconstruct` on those segments maps them later) and counted in its health, never left out silently;
- stop: after SIGTERM it starts no window that would not end before its stop timeout less `stop_reserve_s`
  (the final map's time); the windows it leaves are journalled `skipped` the same way, and it exits 0 with the
  final map of the windows it fitted.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

from mapping.live.window_schedule import window_span, windows_ended

BEHIND = "behind"  # the reasons a skipped window gives
STOP = "stop"


@dataclass
class StopRequest:
    """A stop asked for (SIGTERM, SIGINT) and when: the stop timeout runs from the signal, not from the end of the
    window the worker was fitting when it came. Call it on the signal (daemon.spine.stop_signals.on_signals)."""

    event: threading.Event = field(default_factory=threading.Event)
    at: float | None = None  # time.monotonic() of the first request

    def __call__(self, *_: object) -> None:
        if self.at is None:
            self.at = time.monotonic()
        self.event.set()


def windows_to_skip(next_window: int, distance_m: float, before_m: float, after_m: float,
                    max_behind_m: float | None) -> int:
    """How many windows from `next_window` on to skip now: those before the newest ended one, when
    `next_window` ended more than `max_behind_m` behind `distance_m` (0 when it did not, or with no limit)."""
    if max_behind_m is None:
        return 0
    _, _, end_m = window_span(next_window, before_m, after_m)
    if distance_m - end_m <= max_behind_m:
        return 0
    return max(0, windows_ended(next_window, distance_m, before_m, after_m) - 1)


def stop_deadline(stopped_at: float, stop_timeout_s: float | None, reserve_s: float) -> float | None:
    """The monotonic time by which the last window must end after a stop requested at `stopped_at` (None: no
    stop timeout, every window is fitted)."""
    if stop_timeout_s is None:
        return None
    return stopped_at + max(0.0, stop_timeout_s - reserve_s)


def window_fits(now: float, deadline: float | None, expected_window_s: float) -> bool:
    """Whether a window expected to take `expected_window_s` ends by `deadline` when started at `now`."""
    return deadline is None or now + expected_window_s <= deadline


def expected_window_s(recent_walls_s: list[float], min_window_wall_s: float) -> float:
    """What the next window is expected to take: the longest of the recent ones (at least the configured floor;
    the floor alone before the first)."""
    return max([min_window_wall_s, *recent_walls_s])
