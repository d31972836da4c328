"""The CAN driver run in a thread of the test process, on a real python-can bus, as the CAN tests drive it."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from daemon.spine.config import CanConfig
from daemon.spine.health import HealthCounters
from drivers.can.can_driver import CanDriverStats, open_can_bus, run_can_driver


@dataclass
class DriverThread:
    """What the driver published ((topic, message) pairs), its health counters and, once it stopped, its stats."""

    health: HealthCounters
    stop: threading.Event
    thread: threading.Thread | None = None
    published: list[tuple[str, object]] = field(default_factory=list)
    stats: CanDriverStats | None = None

    def count(self, topic: str) -> int:
        return sum(1 for t, _ in self.published if t == topic)


@contextmanager
def can_driver_thread(config: CanConfig, dbc: Path, join_s: float = 10.0, **driver_kwargs) -> Iterator[DriverThread]:
    """Start the driver, yield once its bus is open, stop and join it on leaving."""
    run = DriverThread(HealthCounters("can"), threading.Event())
    opened = threading.Event()

    def opening(cfg, **kw):
        bus = open_can_bus(cfg, **kw)
        opened.set()
        return bus

    def target():
        run.stats = run_can_driver(config, dbc, lambda t, m: run.published.append((t, m)), run.stop, run.health,
                                   open_bus=opening, **driver_kwargs)

    run.thread = threading.Thread(target=target, daemon=True)
    run.thread.start()
    try:
        assert opened.wait(5), "the CAN driver did not open its bus"
        yield run
    finally:
        run.stop.set()
        run.thread.join(join_s)
