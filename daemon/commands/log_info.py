"""`roadlog log-info`: per-topic message counts, time span and damage of MCAP log files, and the car the first file
recorded (its source, software, cameras with their intrinsics and extrinsics, Lidar, GNSS). A path that is not an
MCAP file (missing, a folder, a ROS 2 bag, any other file) is one `error:` line and exit status 2."""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter

from daemon.log_format.metadata_records import LOG_TIME_CLOCK_KEY, METADATA_NAME
from daemon.log_format.reader import ReadReport, not_a_log, read_log, read_metadata
from daemon.spine.config import EXIT_CONFIG_ERROR
from daemon.spine.process_logging import error_line


def recorded_car(path: str) -> dict:
    """What the file's `roadlog` metadata record says about where it came from and the car's sensors."""
    meta = read_metadata(path).get(METADATA_NAME)
    if meta is None:
        return {"error": f"no {METADATA_NAME!r} metadata record: not a roadlog log (import it first)"}
    car = {k: meta[k] for k in ("software_version", "source", "host") if k in meta}
    car["log_time_clock"] = meta.get(LOG_TIME_CLOCK_KEY, "host_monotonic")  # utc, or a log from before UTC log times
    try:
        car.update(json.loads(meta.get("calibration", "{}")))
    except json.JSONDecodeError as exc:
        car["calibration_error"] = str(exc)
    return car


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
                   "bytes": f.bytes_total, "bytes_skipped": f.bytes_skipped, "damaged_chunks": f.damaged_chunks,
                   "undecodable": f.undecodable, **({"error": f.error} if f.error else {})}
                  for f in report.files],
        "messages_per_topic": dict(sorted(counts.items())),
        "duration_s": (last - first) / 1e9 if first is not None else 0.0,
        "recorded": recorded_car(paths[0]) if paths else {},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog log-info", description=__doc__)
    parser.add_argument("logs", nargs="+", help="MCAP files")
    args = parser.parse_args(argv)
    problems = [why for why in map(not_a_log, args.logs) if why]
    for why in problems:
        print(error_line(why), file=sys.stderr)
    if problems:
        return EXIT_CONFIG_ERROR
    summary = summarise(args.logs)
    print(json.dumps(summary, indent=2))
    if not summary["messages_per_topic"] and "error" in summary["recorded"]:
        print(error_line(f"{args.logs[0]}: {summary['recorded']['error']}"), file=sys.stderr)
        return EXIT_CONFIG_ERROR
    return 0
