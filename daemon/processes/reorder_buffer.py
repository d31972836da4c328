"""The recorder's reorder buffer: messages read from many rings in turn, given to the writer in host-time order.

The recorder reads each topic's ring in bursts, and a ring it fell behind on hands it messages seconds older than
what another ring just gave. The buffer holds what it reads and releases it oldest first once nothing older can
still come: older than every ring's reading position (`safe_ns`, from the rings the recorder read to their end and
those it is still behind on), or more than `window_ns` older than the newest message it holds (None: no such
window, for messages whose rings' bounds are exact), or when it holds more than `max_bytes`. A message older than
one already released (a ring more than the window behind) is late: it is not held (the caller writes it at once,
never drops it) and counted per topic.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator

MESSAGE_OVERHEAD_BYTES = 64  # what a held message costs besides its bulk data


def held_bytes(message: object) -> int:
    return len(getattr(message, "data", b"")) + MESSAGE_OVERHEAD_BYTES


class ReorderBuffer:
    """Messages by host time (their host_mono_ns), released in that order."""

    def __init__(self, window_ns: int | None, max_bytes: int):
        self.window_ns = window_ns
        self.max_bytes = max_bytes
        self._heap: list[tuple[int, int, str, object]] = []
        self._counter = 0
        self.bytes_held = 0
        self.newest_ns: int | None = None
        self.released_ns: int | None = None  # the host time of the last message released
        self.late: dict[str, int] = {}  # per topic: messages older than one already released

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, topic: str, message) -> bool:
        """Hold a message; False (and counted late) when it is older than one already released: write it now."""
        t = int(message.host_mono_ns)
        if self.released_ns is not None and t < self.released_ns:
            self.late[topic] = self.late.get(topic, 0) + 1
            return False
        heapq.heappush(self._heap, (t, self._counter, topic, message))
        self._counter += 1
        self.bytes_held += held_bytes(message)
        self.newest_ns = t if self.newest_ns is None else max(self.newest_ns, t)
        return True

    def pop_ready(self, safe_ns: int | None = None) -> Iterator[tuple[str, object]]:
        """Release, oldest first, what is at or before `safe_ns`, more than the window older than the newest held
        message, or over the byte budget."""
        if not self._heap:
            return
        bounds = [b for b in (None if self.window_ns is None else self.newest_ns - self.window_ns, safe_ns)
                  if b is not None]
        limit = max(bounds) if bounds else None
        while self._heap and ((limit is not None and self._heap[0][0] <= limit) or self.bytes_held > self.max_bytes):
            yield self._pop()

    def drain(self) -> Iterator[tuple[str, object]]:
        """Release everything, oldest first (at stop)."""
        while self._heap:
            yield self._pop()

    def _pop(self) -> tuple[str, object]:
        t, _, topic, message = heapq.heappop(self._heap)
        self.bytes_held -= held_bytes(message)
        self.released_ns = t if self.released_ns is None else max(self.released_ns, t)
        return topic, message
