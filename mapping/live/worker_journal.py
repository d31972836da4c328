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
from pathlib import Path

JOURNAL_NAME = "journal.jsonl"
LEGACY_JOURNAL_NAME = "journal.json"
VERSION = 2
_STATE_KEYS = ("next_window", "mapped_until_m", "origin", "odometry_last_speed_mps", "finished")


def new_state(header: dict) -> dict:
    """The state of a journal holding only `header`."""
    return dict(header, windows=[], next_window=0, odometry_t=[], odometry_s=[], odometry_last_speed_mps=0.0,
                mapped_until_m=0.0, origin=None, finished=False, skipped_lines=0)


def read_journal(folder: Path) -> dict | None:
    """The journal's state in `folder` (header fields, `windows`, `next_window`, `odometry_t`, `odometry_s`,
    `odometry_last_speed_mps`, `mapped_until_m`, `origin`, `finished`, `skipped_lines`: unreadable lines
    passed over), or None if there is none."""
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
                state = new_state(line)
                continue
            if "window" in line:
                state["windows"].append(line["window"])
            if "odometry_from" in line:
                start = line["odometry_from"]
                state["odometry_t"][start:] = line["odometry_t"]
                state["odometry_s"][start:] = line["odometry_s"]
            state.update({k: line[k] for k in _STATE_KEYS if k in line})
    if state is not None:
        state["skipped_lines"] = skipped
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


def progress_line(state: dict, odometry_t: list[int], odometry_s: list[float], odometry_saved: int,
                  window: dict | None = None) -> dict:
    """The line recording `window` (if any) and the progress in `state`, with the odometry knots from the
    last one already saved (it may have moved) on."""
    start = max(0, odometry_saved - 1)
    line = {k: state[k] for k in _STATE_KEYS}
    line.update(odometry_from=start, odometry_t=odometry_t[start:], odometry_s=odometry_s[start:])
    if window is not None:
        line["window"] = window
    return line


def _convert_legacy(legacy: Path, path: Path) -> None:
    old = json.loads(legacy.read_text())
    header = {k: v for k, v in old.items() if k not in _STATE_KEYS + ("windows", "odometry_t", "odometry_s")}
    header["version"] = VERSION
    folder = path.parent
    append_line(folder, header)
    for window in old.get("windows", []):
        append_line(folder, {"window": window})
    state = new_state(header)
    state.update({k: old[k] for k in _STATE_KEYS if k in old})
    append_line(folder, progress_line(state, old.get("odometry_t", []), old.get("odometry_s", []), 0))
    legacy.rename(legacy.with_suffix(".json.converted"))
