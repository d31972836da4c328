"""Recovery: rewrite the complete records of a truncated log file into a valid, closed one."""

from __future__ import annotations

from pathlib import Path

from daemon.log_format.metadata_records import METADATA_NAME
from daemon.log_format.reader import FileReport, ReadReport, read_log, read_metadata
from daemon.log_format.writer import LogWriter
from daemon.spine.config import CarConfig


def recover_log(src: str | Path, dst: str | Path, config: CarConfig) -> FileReport:
    """Rewrite a truncated file's complete records into a valid, closed file (with the source's own metadata:
    its config, host and start time); return what was kept."""
    report = ReadReport()
    metadata = dict(read_metadata(src, until=METADATA_NAME).get(METADATA_NAME, {}), recovered_from=str(src))
    with LogWriter(dst, config, metadata=metadata) as writer:
        for rec in read_log([src], report=report):
            writer.write(rec.topic, rec.message)
    return report.files[0]
