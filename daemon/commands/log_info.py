"""`roadlog log-info`: per-topic message counts, time span and damage of MCAP log files."""

from __future__ import annotations

import argparse
import json
from collections import Counter

from daemon.log_format.reader import ReadReport, read_log


def summarise(paths: list[str]) -> dict:
    report = ReadReport()
    counts: Counter[str] = Counter()
    first = last = None
    for rec in read_log(paths, report=report):
        counts[rec.topic] += 1
        first = rec.log_time_ns if first is None else first
        last = rec.log_time_ns
    return {
        "files": [{"path": str(f.path), "complete": f.complete, "messages": f.messages,
                   "bytes": f.bytes_total, "bytes_skipped": f.bytes_skipped, "undecodable": f.undecodable}
                  for f in report.files],
        "messages_per_topic": dict(sorted(counts.items())),
        "duration_s": (last - first) / 1e9 if first is not None else 0.0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog log-info", description=__doc__)
    parser.add_argument("logs", nargs="+", help="MCAP files")
    args = parser.parse_args(argv)
    print(json.dumps(summarise(args.logs), indent=2))
    return 0
