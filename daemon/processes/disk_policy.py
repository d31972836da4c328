"""The recorder's disk policy: how much space to keep free, which closed segments to delete for it.

Everything here is a pure function of sizes and names except `disk_usage`, the one call that asks the
file system. Setting ROADLOG_SIMULATED_DISK_BYTES makes `disk_usage` report a disk of that size that
holds only the given folder (free = size - bytes under the folder), so tests can fill a "small disk"
without filling the real one.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

SIMULATED_DISK_ENV = "ROADLOG_SIMULATED_DISK_BYTES"
GIB = 1024**3


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
        return DiskUsage(size, max(0, size - _bytes_under(Path(folder))))
    usage = shutil.disk_usage(folder)
    return DiskUsage(usage.total, usage.free)


def required_free_bytes(total_bytes: int, min_free_gib: float, min_free_pct: float) -> int:
    """The free space to keep: both the absolute and the relative floor hold."""
    return int(max(min_free_gib * GIB, min_free_pct / 100.0 * total_bytes))


def segments_to_delete(closed: list[Segment], free_bytes: int, required_bytes: int) -> list[Segment]:
    """The oldest closed segments whose deletion brings the free space up to `required_bytes`.

    `closed` must hold closed segments only (never the open one), oldest first. Returns all of them
    when even that is not enough: the caller then stops writing until space returns.
    """
    chosen = []
    for seg in closed:
        if free_bytes >= required_bytes:
            break
        chosen.append(seg)
        free_bytes += seg.size_bytes
    return chosen
