"""The recorder's segment clock: where a segment ends, by the log time of the messages in it, not by the wall clock.

A segment holds `recorder.segment_seconds` of log time: the messages' host_mono_ns, which the writer turns into the
MCAP log_time and which a replay keeps at any rate (moved by one offset). So a log replayed at rate 1, at `max` or on
a loaded machine is cut at the same messages. Only the clock topics move the clock: the drivers' topics and the time
anchors, what a replay plays (`process_table.played_topics`). The others are stamped by processes running now (the
health of every process: today's clock in a replay) or from the sensors' clocks and written in delayed batches (the
viewing clouds, the fused pose); they go into whichever segment is open.

The first clock message starts the first slot of log time; the first one at or after its end starts the next, which
begins where the last one ended (the slots tile the log time) or, after a stretch of no clock message longer than a
segment (a replay of logs far apart), at that message. Live, the recorder's own time anchors (1 Hz) keep the clock
moving when no driver publishes, so an idle segment still closes on time and is complete on disk. There is no
wall-clock timer: a replay waiting for its mapper, or slowed by a busy machine, keeps its segment open and cuts it
where a fast replay does (nothing is at risk: its complete chunks are fsynced, and its source log is on disk).

A bad clock never cuts a segment per message nor keeps one open forever. Live (`now_ns` given), a host time cannot be
ahead of this host's clock (it is stamped on it before the message is published): a message stamped ahead is taken
as stamped now (`ahead`), so the clock never runs ahead of the host's and the anchors move it on. A clock message
stamped before its slot began (a late one, or a clock behind) is written into the open segment and counted
(`before_start`). Replayed messages come in log-time order (the player merges its logs): a replay has such messages
only when the recorder counts them late too.
"""

from __future__ import annotations

from collections.abc import Callable


def _count(counts: dict[str, int], topic: str) -> None:
    counts[topic] = counts.get(topic, 0) + 1


class SegmentClock:
    """The slot of log time the open segment is in. `now_ns`: this host's monotonic clock, live; None in a replay,
    whose host times may run ahead of it (`--rate 2`, `max`)."""

    def __init__(self, segment_s: float, now_ns: Callable[[], int] | None = None):
        self.segment_ns = int(round(segment_s * 1e9))
        self.now_ns = now_ns
        self.start_ns: int | None = None  # where the current slot began (host ns); None before the first message
        self.gaps = 0  # slots begun after more than a segment without a clock message
        self.ahead: dict[str, int] = {}  # per topic: live messages stamped ahead of the host's clock (taken as now)
        self.before_start: dict[str, int] = {}  # per topic: messages stamped before the slot they were written in
        self._segment_ahead: dict[str, int] = {}  # the same since the last segment closed
        self._segment_before_start: dict[str, int] = {}

    def begins_segment(self, topic: str, host_ns: int) -> bool:
        """Whether a clock message of `topic` stamped `host_ns` begins a new slot: the open segment closes before it
        is written. Moves the clock."""
        if self.now_ns is not None:
            limit = self.now_ns()
            if host_ns > limit:
                _count(self.ahead, topic)
                _count(self._segment_ahead, topic)
                host_ns = limit
        if self.start_ns is None:
            self.start_ns = host_ns
            return False
        if host_ns < self.start_ns:
            _count(self.before_start, topic)
            _count(self._segment_before_start, topic)
            return False
        end = self.start_ns + self.segment_ns
        if host_ns < end:
            return False
        if host_ns >= end + self.segment_ns:  # no clock message for more than a segment: the slot starts here
            self.gaps += 1
            end = host_ns
        self.start_ns = end
        return True

    def take_segment_counts(self) -> dict[str, dict[str, int]]:
        """What happened to the clock since the last segment closed (for the closing segment's metadata)."""
        counts = {"clock_ahead_per_topic": dict(sorted(self._segment_ahead.items())),
                  "before_segment_start_per_topic": dict(sorted(self._segment_before_start.items()))}
        self._segment_ahead, self._segment_before_start = {}, {}
        return counts

    def report(self) -> dict:
        """For the recorder's health detail."""
        return {"slot_start_ns": self.start_ns, "gaps": self.gaps, "ahead": dict(sorted(self.ahead.items())),
                "before_start": dict(sorted(self.before_start.items()))}
