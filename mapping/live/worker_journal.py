"""The mapping worker's journal: an append-only JSON-lines file, `<data>/map/journal.jsonl`.

The first line is the header (format version, config path and hash, grid resolution, tile size, cameras).
Every later line is what changed since the line before: a finished window's entry, the wheel-odometry
knots added since (`odometry_from`: the index they start at; the last knot moves on between saves, so
each line rewrites it), and the progress figures. `read_journal` folds the lines into one state.

Appending one line per window keeps a day's drive cheap: a journal rewritten whole after every window
wrote the square of its length (a 12 MB journal 3,600 times over 290 km). A line torn by a power cut is
skipped and counted by `read_journal`; the next append starts on a fresh line, so nothing after it is lost.
A map folder from before this format (`journal.json`, one JSON document) is converted on first read.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Literal

JOURNAL_NAME = "journal.jsonl"
LEGACY_JOURNAL_NAME = "journal.json"
VERSION = 2
_STATE_KEYS = ("next_window", "mapped_until_m", "origin", "odometry_last_speed_mps", "finished")


@dataclass
class JournalHeader:
    """The journal's first line: what the map folder was made with."""

    version: int = VERSION
    config_path: str | None = None
    config_sha256: str | None = None
    grid_resolution_m: float | None = None
    tile_cells: int | None = None
    cameras: list[str] = field(default_factory=list)


@dataclass
class WindowEntry:
    """One window's outcome. A failed window has `error`; a done one its seed, wall time, tiles, metrics and
    provenance (host time range, per-topic seq ranges, log segments, input counts, the config); a skipped one
    (mapping.live.lag_policy: behind the car, or left at the stop) its `reason`, host time range and the log
    segments that hold it (`roadlog reconstruct` on them maps it)."""

    index: int
    status: Literal["done", "failed", "skipped"]
    centre_m: float | None = None  # place on the drive, m
    start_m: float | None = None
    end_m: float | None = None
    attempts: int | None = None
    finished_mono_ns: int | None = None
    error: str | None = None
    reason: str | None = None  # skipped: "behind: ..." or "stop: ..."
    seed: int | None = None
    wall_s: float | None = None
    tiles: list[str] | None = None  # the tile files it wrote
    trajectory_xy_box: list[float] | None = None  # [x_min, y_min, x_max, y_max] of its track, ENU m
    metrics: dict[str, float | int | str | None] | None = None
    host_time_ns: list[int] | None = None
    seq: dict[str, list[int]] | None = None
    segments: list[str] | None = None
    keyframes: int | None = None
    frames: int | None = None  # camera frames in its time span
    frames_without_mask: int | None = None  # of them, those with no mask and no segmentation model
    lidar_packets: int | None = None  # the Lidar messages of the window: packets ...
    lidar_point_clouds: int | None = None  # ... or decoded scans (a point-cloud Lidar)
    lidar_ground_points: int | None = None
    config: dict[str, str] | None = None  # {"path", "sha256"}

    def to_json(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}

    @staticmethod
    def from_json(data: dict) -> WindowEntry:
        return WindowEntry(**data)


@dataclass
class JournalState:
    """The journal's lines folded into one state."""

    header: JournalHeader
    windows: list[WindowEntry] = field(default_factory=list)
    next_window: int = 0
    odometry_t: list[int] = field(default_factory=list)  # wheel-odometry knots: host ns and metres
    odometry_s: list[float] = field(default_factory=list)
    odometry_last_speed_mps: float = 0.0
    mapped_until_m: float = 0.0
    origin: list[float] | None = None  # the local ENU frame's WGS84 origin (lat, lon, alt)
    finished: bool = False
    skipped_lines: int = 0  # unreadable (torn) lines passed over


def _header(line: dict) -> JournalHeader:
    known = {f.name for f in fields(JournalHeader)}
    return JournalHeader(**{k: v for k, v in line.items() if k in known})


def read_journal(folder: Path) -> JournalState | None:
    """The journal's state in `folder`, or None if there is none."""
    path = folder / JOURNAL_NAME
    if not path.exists():
        legacy = folder / LEGACY_JOURNAL_NAME
        if not legacy.exists():
            return None
        _convert_legacy(legacy, path)
    state, skipped = None, 0
    with open(path, "rb") as f:
        for raw in f:
            try:
                line = json.loads(raw)
            except ValueError:  # torn by a crash mid-write: passed over, counted
                skipped += 1
                continue
            if state is None:
                state = JournalState(_header(line))
                continue
            if "window" in line:
                state.windows.append(WindowEntry.from_json(line["window"]))
            if "odometry_from" in line:
                start = line["odometry_from"]
                state.odometry_t[start:] = line["odometry_t"]
                state.odometry_s[start:] = line["odometry_s"]
            for k in _STATE_KEYS:
                if k in line:
                    setattr(state, k, line[k])
    if state is not None:
        state.skipped_lines = skipped
    return state


def append_line(folder: Path, line: dict) -> None:
    """Append one line and make it durable (fsync): on a fresh line even if the last one was torn."""
    with open(folder / JOURNAL_NAME, "ab+") as f:
        if f.tell() > 0:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                f.write(b"\n")
        f.write(json.dumps(line, separators=(",", ":")).encode() + b"\n")
        f.flush()
        os.fsync(f.fileno())


def header_line(header: JournalHeader) -> dict:
    return asdict(header)


def progress_line(state: JournalState, odometry_t: list[int], odometry_s: list[float], odometry_saved: int,
                  window: WindowEntry | None = None) -> dict:
    """The line recording `window` (if any) and the progress in `state`, with the odometry knots from the
    last one already saved (it may have moved) on."""
    start = max(0, odometry_saved - 1)
    line = {k: getattr(state, k) for k in _STATE_KEYS}
    line.update(odometry_from=start, odometry_t=odometry_t[start:], odometry_s=odometry_s[start:])
    if window is not None:
        line["window"] = window.to_json()
    return line


def _convert_legacy(legacy: Path, path: Path) -> None:
    old = json.loads(legacy.read_text())
    header = _header(old)
    header.version = VERSION
    folder = path.parent
    append_line(folder, header_line(header))
    for window in old.get("windows", []):
        append_line(folder, {"window": window})
    state = JournalState(header)
    for k in _STATE_KEYS:
        if k in old:
            setattr(state, k, old[k])
    append_line(folder, progress_line(state, old.get("odometry_t", []), old.get("odometry_s", []), 0))
    legacy.rename(legacy.with_suffix(".json.converted"))
