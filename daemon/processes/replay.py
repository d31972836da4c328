"""The log player: publishes recorded segments into the bus as the live drivers would.

Messages of one or many segments are played in log-time order, paced by their recorded log times
(`--rate 1.0`, or any factor) or as fast as the consumers allow (`--rate max`: every publish is lossless,
so it waits for registered lossless subscribers such as the mapping worker instead of overrunning them).
Each message gets a fresh seq from the publisher; its host_mono_ns is its recorded arrival time moved
onto this host's clock (log time + the offset at the start). A sensor's own stamps are kept, except those
on the recording host's monotonic clock (a topic whose stamps lie within HOST_CLOCK_WITHIN_NS of their
arrival: an OAK camera, the time anchors), which move with the host times: so the relations between every
sensor's clock and the host clock are those of the drive, at any rate, and a consumer cannot tell replay
from a live drive (kept as they were, a camera's stamps looked free-running and its frames were placed at
their arrival, late by the camera's delivery delay). Only the drivers' topics and the time anchors are
played: topics the car's topic table lacks and topics that live processes publish themselves (health,
poses) are skipped and counted. Progress goes once a second, as JSON in `detail`, on the replay's health topic.
"""

from __future__ import annotations

import argparse
import heapq
import json
import logging
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from daemon.bus import pubsub
from daemon.log_format.reader import LogRecord, ReadReport, last_log_time, read_log
from daemon.spine.config import CarConfig, ConfigError, load_config, reports_config_errors
from daemon.spine.health import HealthCounters
from daemon.spine.messages import HOST_CLOCK_WITHIN_NS
from daemon.spine.process_logging import setup_logging
from daemon.spine.process_table import playback_rate, played_topics
from daemon.spine.stop_signals import set_on_signals
from daemon.spine.topics import TIME_ANCHOR, health_topic, topic_table

PROCESS = "replay"
HEALTH_PERIOD_S = 1.0
LOSSLESS_WAIT_SLICE_S = 0.5  # a blocked lossless publish retries in slices so health keeps flowing
log = logging.getLogger(__name__)


def replayed_topics(config: CarConfig) -> set[str]:
    """The topics the car's drivers publish (their health excepted): what a replay stands in for."""
    return played_topics(config) - {TIME_ANCHOR}


def _first_log_time(path: Path) -> int | None:
    records = read_log([path])
    try:
        first = next(records, None)
    finally:
        records.close()
    return None if first is None else first.log_time_ns


@dataclass
class LogSpan:
    """Files ordered by their first message, and the time span they cover (host monotonic ns)."""

    files: list[tuple[int, Path]]
    start_ns: int
    end_ns: int


def log_span(paths: list[Path]) -> LogSpan:
    files = []
    end = 0
    for p in paths:
        first = _first_log_time(p)
        if first is None:
            continue
        files.append((first, p))
        end = max(end, last_log_time(p) or first)
    files.sort()
    start = files[0][0] if files else 0
    return LogSpan(files, start, max(end, start))


def merged_records(span: LogSpan, start_ns: int | None, end_ns: int | None,
                   report: ReadReport) -> Iterator[LogRecord]:
    """All files' records in log-time order, opening each file only when playback reaches it."""
    heap: list = []
    order = 0

    def push(it: Iterator[LogRecord]) -> None:
        nonlocal order
        rec = next(it, None)
        if rec is not None:
            heapq.heappush(heap, (rec.log_time_ns, order, rec, it))
            order += 1

    pending = list(span.files)
    while heap or pending:
        while pending and (not heap or pending[0][0] <= heap[0][0]):
            push(read_log([pending.pop(0)[1]], start_ns=start_ns, end_ns=end_ns, report=report))
        if heap:
            _, _, rec, it = heapq.heappop(heap)
            yield rec
            push(it)


@dataclass
class ReplayProgress:
    log_start_ns: int = 0
    log_end_ns: int = 0
    reached_ns: int = 0
    published: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    report: ReadReport = field(default_factory=ReadReport)
    wall_s: float = 0.0

    def fraction(self) -> float:
        span = self.log_end_ns - self.log_start_ns
        return 1.0 if span <= 0 else min(1.0, max(0.0, (self.reached_ns - self.log_start_ns) / span))

    def detail(self) -> str:
        return json.dumps({
            "log_time_s": (self.reached_ns - self.log_start_ns) / 1e9 if self.reached_ns else 0.0,
            "log_duration_s": (self.log_end_ns - self.log_start_ns) / 1e9,
            "fraction": round(self.fraction(), 4),
            "published": sum(self.published.values()),
            "published_per_topic": dict(sorted(self.published.items())),
            "skipped_per_topic": dict(sorted(self.skipped.items())),
            "incomplete_files": [str(p) for p in self.report.incomplete_files],
            "damaged_chunks": sum(f.damaged_chunks for f in self.report.files),
            "bytes_skipped": self.report.bytes_skipped,
        })


class _Player:
    """Publishers per topic, health, and the clock that paces the playback."""

    def __init__(self, config: CarConfig, progress: ReplayProgress, lossless: bool, stop: threading.Event):
        self.config = config
        self.progress = progress
        self.lossless = lossless
        self.stop = stop
        self.health = HealthCounters(PROCESS)
        self.publishers: dict[str, pubsub.Publisher] = {}
        self.health_pub = pubsub.open_publisher(config, health_topic(PROCESS))
        self.last_health = 0.0

    def publish_health(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self.last_health >= HEALTH_PERIOD_S:
            self.last_health = now
            msg = self.health.snapshot()
            msg.detail = self.progress.detail()
            self.health_pub.publish(msg)

    def wait_until(self, target_mono_ns: int) -> None:
        while not self.stop.is_set():
            self.publish_health()
            delay = (target_mono_ns - time.monotonic_ns()) / 1e9
            if delay <= 0:
                return
            self.stop.wait(min(delay, HEALTH_PERIOD_S))

    def publish(self, topic: str, message: object, host_mono_ns: int) -> bool:
        """Publish as a live driver would; False when stopped while waiting for a lossless reader."""
        pub = self.publishers.get(topic)
        if pub is None:
            pub = self.publishers[topic] = pubsub.open_publisher(self.config, topic)
        message.host_mono_ns = host_mono_ns
        while True:
            try:
                pub.publish(message, lossless=self.lossless, timeout_s=LOSSLESS_WAIT_SLICE_S)
                break
            except TimeoutError:
                self.publish_health()
                if self.stop.is_set():
                    return False
        self.health.count_published()
        self.progress.published[topic] = self.progress.published.get(topic, 0) + 1
        self.publish_health()
        return True

    def close(self) -> None:
        self.publish_health(force=True)
        for pub in self.publishers.values():
            pub.close()
        self.health_pub.close()


def replay(config: CarConfig, paths: list[str | Path], *, rate: float | None = 1.0, start_s: float = 0.0,
           end_s: float | None = None, stop: threading.Event | None = None) -> ReplayProgress:
    """Play the logs into the bus; rate None = as fast as lossless consumers allow. Returns the tally."""
    stop = stop or threading.Event()
    span = log_span(sorted(Path(p) for p in paths))
    start_ns = span.start_ns + int(start_s * 1e9)
    end_ns = None if end_s is None else span.start_ns + int(end_s * 1e9)
    progress = ReplayProgress(log_start_ns=start_ns, log_end_ns=span.end_ns if end_ns is None else min(end_ns,
                                                                                                      span.end_ns))
    table = topic_table(config)
    playable = played_topics(config)
    player = _Player(config, progress, lossless=rate is None, stop=stop)
    wall0 = time.monotonic_ns()
    shift = wall0 - start_ns  # recorded host times -> this host's clock
    host_clocked: dict[str, bool] = {}  # per topic, from its first message: stamps on the recording host's clock
    try:
        for rec in merged_records(span, start_ns, end_ns, progress.report):
            if stop.is_set():
                break
            spec = table.get(rec.topic)
            if rec.topic not in playable or type(rec.message) is not spec.message_type:
                progress.skipped[rec.topic] = progress.skipped.get(rec.topic, 0) + 1
            else:
                if rate is not None:
                    player.wait_until(wall0 + int((rec.log_time_ns - start_ns) / rate))
                if host_clocked.setdefault(rec.topic,
                                           abs(rec.message.sensor_time_ns - rec.log_time_ns) < HOST_CLOCK_WITHIN_NS):
                    rec.message.sensor_time_ns += shift
                if not player.publish(rec.topic, rec.message, rec.log_time_ns + shift):
                    break
            progress.reached_ns = rec.log_time_ns
    finally:
        progress.wall_s = (time.monotonic_ns() - wall0) / 1e9
        player.close()
    return progress


def _rate(text: str) -> float | None:
    try:
        return playback_rate(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog replay", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("logs", nargs="+", help="MCAP segments")
    parser.add_argument("--rate", type=_rate, default=1.0, help="playback speed factor, or 'max' (default 1.0)")
    parser.add_argument("--start", type=float, default=0.0, help="seconds from the log start")
    parser.add_argument("--end", type=float, default=None, help="seconds from the log start")
    args = parser.parse_args(argv)
    setup_logging("replay")
    config = load_config(args.config)
    missing = [p for p in args.logs if not Path(p).is_file()]
    if missing:
        raise ConfigError(f"no such log file: {', '.join(missing)}")
    stop = threading.Event()
    set_on_signals(stop)
    progress = replay(config, args.logs, rate=args.rate, start_s=args.start, end_s=args.end, stop=stop)
    log.info("replayed %d messages in %.1f s (%s)", sum(progress.published.values()), progress.wall_s,
             progress.detail())
    return 0


if __name__ == "__main__":
    sys.exit(main())
