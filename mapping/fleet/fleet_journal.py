"""The fleet job's journal, `DIR/journal/<drive id>/`: `drive.json` (its logs, window count, ENU origin, time to
read it) once the drive's inputs were read, and `w<k>.json` per window: `done` (what it wrote: tiles, cells,
metrics, attempts, wall time) or `failed` (each attempt's error). A window marked done is never fitted again;
a failed one is tried again by the next run. Every file is written atomically (tile_store.save_json)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from mapping.fleet.tile_store import save_json


@dataclass(frozen=True)
class FleetJournal:
    root: Path  # the job's DIR

    def folder(self, drive: str) -> Path:
        return self.root / "journal" / drive

    def drive(self, drive: str) -> dict | None:
        return _read(self.folder(drive) / "drive.json")

    def write_drive(self, drive: str, entry: dict) -> None:
        save_json(self.folder(drive) / "drive.json", entry)

    def window(self, drive: str, k: int) -> dict | None:
        return _read(self.folder(drive) / f"w{k}.json")

    def write_window(self, drive: str, k: int, entry: dict) -> None:
        save_json(self.folder(drive) / f"w{k}.json", entry)

    def done(self, drive: str, k: int) -> bool:
        entry = self.window(drive, k)
        return entry is not None and entry.get("status") == "done"

    def progress(self) -> tuple[int, int, int]:
        """(windows done, windows failed, windows known) over every drive read so far."""
        done = failed = known = 0
        for folder in sorted((self.root / "journal").glob("*")):
            drive = _read(folder / "drive.json")
            if drive is None:
                continue
            known += drive["windows"]
            for k in range(drive["windows"]):
                status = (_read(folder / f"w{k}.json") or {}).get("status")
                done += status == "done"
                failed += status == "failed"
        return done, failed, known


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):  # absent (or, never after an atomic write, torn)
        return None
