"""The recorder's disk policy: how much space to keep free, which closed segments it may delete for it, and whether
a deletion did free space.

A segment is deleted only while deleting frees space toward the target: one segment at first, then twice as many
each time the space of the last ones stayed free for JUDGE_AFTER_S (so the free-space target must hold that long
of writing). When the bytes of a deletion do not come back as free space, or are gone again by then (another
program writing to the disk takes them), deleting stops for a hold-off that doubles with each such deletion in a
row (FIRST_HOLD_OFF_S up to MAX_HOLD_OFF_S): such a program costs about the free-space target and then a segment
per hold-off, not every recording, and a program that filled the disk once costs a short pause. The newest
segments that together hold `recorder.keep_newest_s` seconds of drive are never deleted (the floor): below it the
recorder stops writing instead.

Everything here is a pure function of sizes and names except `disk_usage`, the one call that asks the
file system. Setting ROADLOG_SIMULATED_DISK_BYTES makes `disk_usage` report a disk of that size that
holds only the given folder (free = size - bytes under the folder), so tests can fill a "small disk"
without filling the real one.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

SIMULATED_DISK_ENV = "ROADLOG_SIMULATED_DISK_BYTES"
GIB = 1024**3
JUDGE_AFTER_S = 0.5  # whether a deletion's space stayed free is judged this long after it (no deletion meanwhile)
MAX_BATCH = 64  # one segment at first, twice as many each time their space stayed free, up to this
FIRST_HOLD_OFF_S = 2.0  # after a deletion whose space another program took, no deletion for this long,
MAX_HOLD_OFF_S = 300.0  # twice as long after each further one in a row, up to this
FREED_FRACTION = 0.5  # a deletion frees space when at least this part of its bytes comes back free


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


def hold_off_s(undone_in_a_row: int) -> float:
    """How long to wait before deleting again after `undone_in_a_row` deletions whose space was taken."""
    return min(MAX_HOLD_OFF_S, FIRST_HOLD_OFF_S * 2 ** max(0, undone_in_a_row - 1))
