"""A CAN bus that hands out a list of frames, then sets a stop event: python-can's interface as run_can_driver uses it
(recv, shutdown), for the CAN fuzz test and bench/parser_fuzz.py."""

from __future__ import annotations

import threading

import can


class ListBus:
    """Hands out the given frames one per recv, then sets `stop` and returns None (duck-typed like can.BusABC)."""

    def __init__(self, frames: list[can.Message], stop: threading.Event):
        self.frames, self.stop = list(frames), stop

    def recv(self, timeout=None):
        if self.frames:
            return self.frames.pop(0)
        self.stop.set()
        return None

    def shutdown(self):
        pass
