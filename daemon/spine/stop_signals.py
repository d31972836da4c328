"""What a process does on SIGTERM/SIGINT, run outside the signal handler.

A Python signal handler runs in the main thread between two of its bytecodes, also while that thread holds a lock:
inside `threading.Event.wait` the event's own (non-reentrant) lock is held for a few bytecodes before and after the
wait. A handler that sets that event then blocks on the lock its own thread holds, forever: the process ignores
every later SIGTERM and only SIGKILL ends it (cpython issue 126434 is the same for multiprocessing.Event). The daemon
did this once in CI: the supervisor logged the SIGTERM and never stopped. So the handler here only writes the
signal's number into a pipe; a relay thread reads it and runs the process's callback, which may take any lock.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterable

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def on_signals(callback: Callable[[int], object], signals: Iterable[int] = STOP_SIGNALS) -> None:
    """Run `callback(signum)` in a relay thread whenever one of `signals` arrives (call from the main thread)."""
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)

    def relay() -> None:
        while True:
            received = os.read(read_end, 64)
            if not received:
                return
            for signum in received:
                callback(signum)

    threading.Thread(target=relay, daemon=True, name="signal-relay").start()

    def handler(signum: int, _frame: object) -> None:
        try:
            os.write(write_end, bytes([signum]))
        except BlockingIOError:  # 64 KiB of signals the relay has not read yet: it has a stop to run already
            pass

    for signum in signals:
        signal.signal(signum, handler)


def set_on_signals(event: threading.Event, signals: Iterable[int] = STOP_SIGNALS) -> None:
    """Set `event` when one of `signals` arrives."""
    on_signals(lambda _signum: event.set(), signals)
