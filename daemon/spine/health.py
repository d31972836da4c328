"""Per-process health counters, turned into a DriverHealth message once a second, and a process's memory."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from daemon.spine.messages import DriverHealth


@dataclass
class HealthCounters:
    """What a driver received, published, dropped, rejected, and the errors it met (with the last one)."""

    process: str
    expected_rate_hz: float = 0.0
    received: int = 0
    published: int = 0
    dropped: int = 0
    rejected: int = 0
    errors: int = 0
    sequence_gaps: int = 0
    last_error: str = ""
    last_message_mono_ns: int = 0
    _recent: deque = field(default_factory=lambda: deque(maxlen=4096))

    def count_published(self, n: int = 1, now_ns: int | None = None) -> None:
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        self.published += n
        self.last_message_mono_ns = now_ns
        self._recent.append((now_ns, n))

    def count_error(self, what: str) -> None:
        self.errors += 1
        self.last_error = what

    def count_rejected(self, what: str, n: int = 1) -> None:
        self.rejected += n
        self.last_error = what

    def rate_hz(self, now_ns: int | None = None, window_s: float = 2.0) -> float:
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        start = now_ns - int(window_s * 1e9)
        while self._recent and self._recent[0][0] < start:
            self._recent.popleft()
        return sum(n for _, n in self._recent) / window_s

    def snapshot(self, now_ns: int | None = None) -> DriverHealth:
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        rate = self.rate_hz(now_ns)
        age = (now_ns - self.last_message_mono_ns) / 1e9 if self.last_message_mono_ns else float("inf")
        state = "ok"
        if self.expected_rate_hz > 0 and rate < 0.5 * self.expected_rate_hz:
            state = "degraded"
        if self.last_message_mono_ns == 0 or age > 5.0:
            state = "error" if self.expected_rate_hz > 0 else state
        return DriverHealth(
            sensor_time_ns=now_ns,
            host_mono_ns=now_ns,
            process=self.process,
            state=state,
            rate_hz=rate,
            last_message_age_s=age,
            received=self.received,
            published=self.published,
            dropped=self.dropped,
            rejected=self.rejected,
            errors=self.errors,
            sequence_gaps=self.sequence_gaps,
            detail=self.last_error,
        )


def process_memory_mb(pid: int | str = "self") -> dict[str, float]:
    """A process's current (VmRSS) and peak (VmHWM) resident memory in MB, from /proc (empty for a zombie).
    VmHWM is the process's own peak: ru_maxrss starts from the parent's, which execve keeps."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024.0
    return out
