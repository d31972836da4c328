"""Where an importer writes: a log that appears whole or not at all (OUT.partial renamed over OUT when the import
finishes, removed when it fails), and the summary every importer prints."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from daemon.log_format.writer import LogWriter
from daemon.spine.config import CarConfig


@dataclass(frozen=True)
class ImportSummary:
    log: Path
    messages: dict[str, int]  # per topic
    drive_s: float  # first to last camera frame
    wall_s: float  # the import's own time

    def as_json(self) -> str:
        return json.dumps({"log": str(self.log), "messages": self.messages, "drive_s": round(self.drive_s, 3),
                           "wall_s": round(self.wall_s, 3)})


@contextlib.contextmanager
def imported_log(out: Path, config: CarConfig, metadata: dict[str, str]) -> Iterator[LogWriter]:
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    writer = LogWriter(partial, config, metadata=metadata)
    try:
        yield writer
    except BaseException:
        writer.close()
        partial.unlink(missing_ok=True)
        raise
    writer.close()
    partial.replace(out)
