"""The recorder's disk policy: how much space to keep free, which closed segments it may delete for it, and whether
a deletion did free space.

A segment is deleted only while deleting frees space toward the target: one segment at first, then twice as many
each time the space of the last ones stayed free for JUDGE_AFTER_S (so the free-space target must hold that long
of writing). When the bytes of a deletion do not come back as free space, or are gone again by then (another
program writing to the disk takes them), deleting stops for a hold-off that doubles with each such deletion in a
row (`recorder.deletion_hold_off_s`: the first, then twice as long, up to the last): such a program costs about the
free-space target and then a segment per hold-off, not every recording, and a program that filled the disk once
costs a short pause. The newest segments that together hold `recorder.keep_newest_s` seconds of drive are never
deleted (the floor): below it the recorder stops writing instead.

`SegmentDeleter` keeps that rule's state across the recorder's disk checks and counts what it deleted; the hold-off
(until when, on the wall clock, and how many undone deletions in a row) is also kept in STATE_FILE in the data
folder, so a restarted recorder keeps pausing instead of deleting at once again. The rest are pure functions of
sizes and names except `disk_usage`, the one call that asks the file system. Setting ROADLOG_SIMULATED_DISK_BYTES
makes `disk_usage` report a disk of that size that holds only the given folder (free = size - bytes under the
folder), so tests can fill a "small disk" without filling the real one.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

SIMULATED_DISK_ENV = "ROADLOG_SIMULATED_DISK_BYTES"
GIB = 1024**3
JUDGE_AFTER_S = 0.5  # whether a deletion's space stayed free is judged this long after it (no deletion meanwhile)
MAX_BATCH = 64  # one segment at first, twice as many each time their space stayed free, up to this
FREED_FRACTION = 0.5  # a deletion frees space when at least this part of its bytes comes back free
STATE_FILE = "disk-policy-state.json"  # in the data folder: the hold-off, across recorder restarts
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DiskUsage:
    total_bytes: int
    free_bytes: int


@dataclass(frozen=True)
class Segment:
    """A closed log segment on disk (name order is time order)."""

    path: Path
    size_bytes: int


def _bytes_under(folder: Path) -> int:
    total = 0
    for entry in folder.rglob("*"):
        try:
            if entry.is_file():
                total += entry.stat().st_size
        except FileNotFoundError:  # deleted while we walked
            continue
    return total


def disk_usage(folder: str | Path) -> DiskUsage:
    """Size and free space of the file system holding `folder` (or of the simulated disk, see above)."""
    simulated = os.environ.get(SIMULATED_DISK_ENV)
    if simulated:
        size = int(simulated)
        return DiskUsage(size, size - _bytes_under(Path(folder)))  # below 0 when over: a deletion still shows
    usage = shutil.disk_usage(folder)
    return DiskUsage(usage.total, usage.free)


def required_free_bytes(total_bytes: int, min_free_gib: float, min_free_pct: float) -> int:
    """The free space to keep: both the absolute and the relative floor hold."""
    return int(max(min_free_gib * GIB, min_free_pct / 100.0 * total_bytes))


def deletable(closed: list[Segment], drive_seconds: Callable[[Segment], float], keep_newest_s: float) -> list[Segment]:
    """The segments the policy may delete, oldest first: `closed` (closed or quarantined segments only, never the
    open one, oldest first) without the newest ones that together hold `keep_newest_s` seconds of drive."""
    kept_s, n = 0.0, len(closed)
    while n and kept_s < keep_newest_s:
        n -= 1
        kept_s += drive_seconds(closed[n])
    return closed[:n]


def freed(free_before: int, free_after: int, own_bytes_written: int, deleted_bytes: int) -> bool:
    """Whether deleting `deleted_bytes` freed space: the free space rose (counting what the recorder itself wrote
    meanwhile as its own use) by at least FREED_FRACTION of what was deleted."""
    return free_after - free_before + own_bytes_written >= FREED_FRACTION * deleted_bytes


def hold_off_s(undone_in_a_row: int, first_s: float, max_s: float) -> float:
    """How long to wait before deleting again after `undone_in_a_row` deletions whose space was taken: `first_s`
    after the first, twice as long after each further one, up to `max_s`."""
    return min(max_s, first_s * 2 ** max(0, undone_in_a_row - 1))


class SegmentDeleter:
    """The deletion rule above across disk checks: which segments to delete now, whether the last ones freed space,
    and what it deleted since the recorder started (segments, seconds of drive, bytes)."""

    def __init__(self, keep_newest_s: float, listing: Callable[[], list[Segment]],
                 drive_seconds: Callable[[Path], float], count_error: Callable[[str], None],
                 state_path: Path | None = None, hold_off: tuple[float, float] = (2.0, 300.0)):
        self.keep_newest_s = keep_newest_s
        self.hold_off = hold_off  # (first, longest) seconds: recorder.deletion_hold_off_s
        self._state_path = state_path  # where the hold-off is kept across restarts (None: not kept)
        self._listing = listing  # the closed and quarantined segments, oldest first
        self._read_seconds = drive_seconds
        self._count_error = count_error
        self.segments = 0
        self.seconds = 0.0  # of drive, in the deleted segments
        self.bytes = 0
        self.undone = 0  # deletions whose space another program took
        self.at_floor = False  # a deficit only the newest keep_newest_s of drive could pay: nothing deleted
        self._hold_off_until = 0.0
        self._undone_in_a_row = 0
        self._batch = 1  # segments one round may delete: doubles while their space stays free
        self._last_round: tuple[float, int, int, int] | None = None  # (when, free before, own bytes, bytes deleted)
        self._seconds: dict[Path, float] = {}
        self._restore_hold_off()

    def _restore_hold_off(self) -> None:
        """Take up the hold-off an earlier recorder left in the state file (an unreadable one is counted, ignored)."""
        if self._state_path is None or not self._state_path.exists():
            return
        try:
            state = json.loads(self._state_path.read_text())
            until, in_a_row = float(state["hold_off_until_unix_s"]), int(state["undone_in_a_row"])
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            why = f"disk policy: {self._state_path.name} unreadable ({exc}): no hold-off taken up"
            self._count_error(why)
            log.error("%s", why)
            return
        left = min(max(0.0, until - time.time()), self.hold_off[1])  # a clock set back cannot make it longer
        self._undone_in_a_row = max(0, in_a_row)
        self._hold_off_until = time.monotonic() + left
        if left > 0:
            log.warning("disk policy: held off for %.0f more s (a deletion before the restart freed nothing)", left)

    def _save_hold_off(self) -> None:
        if self._state_path is None:
            return
        left = max(0.0, self._hold_off_until - time.monotonic())
        tmp = self._state_path.with_name(self._state_path.name + ".tmp")
        try:
            tmp.write_text(json.dumps({"hold_off_until_unix_s": time.time() + left,
                                       "undone_in_a_row": self._undone_in_a_row}))
            os.replace(tmp, self._state_path)
        except OSError as exc:  # a full disk is when this matters most: counted, the pause still holds in memory
            self._count_error(f"disk policy: saving {self._state_path.name}: {exc}")

    @property
    def judging(self) -> bool:
        """Deletions were made that are not judged yet (more may follow)."""
        return self._last_round is not None

    def _drive_seconds(self, seg: Segment) -> float:
        if seg.path not in self._seconds:
            self._seconds[seg.path] = self._read_seconds(seg.path)
        return self._seconds[seg.path]

    def _undone(self, why: str) -> None:
        self.undone += 1
        self._undone_in_a_row += 1
        self._batch = 1
        hold_off = hold_off_s(self._undone_in_a_row, *self.hold_off)
        self._hold_off_until = time.monotonic() + hold_off
        self._last_round = None
        self._save_hold_off()
        self._count_error(f"disk policy: {why}")
        log.error("disk policy: %s: another program takes the space; no deletion for %.0f s", why, hold_off)

    def make_room(self, usage: DiskUsage, required: int, own_bytes: int) -> int:
        """Delete the oldest segments the rule allows toward `required` free bytes, `own_bytes` being all the
        recorder has written so far; the free bytes after."""
        free, now = usage.free_bytes, time.monotonic()
        if self._last_round is not None:  # did the space of the last deletions stay free?
            when, before, own_then, deleted = self._last_round
            if now - when < JUDGE_AFTER_S:
                return free  # too early to tell: no more deletions meanwhile
            self._last_round = None
            if freed(before, free, own_bytes - own_then, deleted):
                if self._undone_in_a_row:
                    self._undone_in_a_row = 0
                    self._save_hold_off()
                self._batch = min(2 * self._batch, MAX_BATCH)
            else:
                self._undone(f"the {deleted} bytes deleted {now - when:.1f} s ago were taken again ({before} bytes "
                             f"free before, {free} now)")
        if free >= required or now < self._hold_off_until:
            self.at_floor = False
            return free
        round_start, deleted_now = free, 0
        candidates = deletable(self._listing(), self._drive_seconds, self.keep_newest_s)
        for seg in candidates[: self._batch]:
            if free >= required:
                break
            seconds = self._drive_seconds(seg)
            try:
                seg.path.unlink()
            except FileNotFoundError:
                continue
            except OSError as exc:
                self._count_error(f"deleting {seg.path.name}: {exc}")
                continue
            self._seconds.pop(seg.path, None)
            after = disk_usage(seg.path.parent).free_bytes
            self.segments += 1
            self.seconds += seconds
            self.bytes += seg.size_bytes
            deleted_now += seg.size_bytes
            log.warning("disk policy: deleted %s (%.1f s of drive, %d bytes): %d -> %d bytes free, %d required",
                        seg.path.name, seconds, seg.size_bytes, free, after, required)
            if not freed(free, after, 0, seg.size_bytes):
                self._undone(f"deleting {seg.path.name} freed {after - free} of its {seg.size_bytes} bytes")
                return after
            free = after
        if deleted_now:
            self._last_round = (time.monotonic(), round_start, own_bytes, deleted_now)
        at_floor = free < required and not self._last_round and all(not seg.path.exists() for seg in candidates)
        if at_floor and not self.at_floor:
            log.error("disk policy: only the newest %.0f s of drive are left to delete (recorder.keep_newest_s): "
                      "they are kept", self.keep_newest_s)
        self.at_floor = at_floor
        return free

    def report(self) -> dict[str, float]:
        """What it deleted and where it stands, for the recorder's health detail (numbers only: /metrics)."""
        return {"deleted_segments": self.segments, "deleted_drive_s": round(self.seconds, 3),
                "deleted_bytes": self.bytes, "deletions_undone": self.undone,
                "held_off_s": round(max(0.0, self._hold_off_until - time.monotonic()), 1),
                "at_floor": int(self.at_floor), "keep_newest_s": self.keep_newest_s}
