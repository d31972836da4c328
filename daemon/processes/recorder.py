"""The recorder process: every logged topic from the bus into time-named, self-contained MCAP segments.

A segment is written as `roadlog_<UTC now>_<index>.mcap.open` and renamed once closed to `.mcap`, named by the UTC of
its first message where the time anchors give it (a replay's segments carry the drive's date). It is rotated once its
messages span `recorder.segment_seconds` of log time (segment_clock.py: the messages' own time, so a replay is cut at
the same messages at any rate or load), or at `recorder.segment_bytes`; once a second its chunk in progress is finished
and the file fsynced (a slow topic's messages do not wait in memory for a full chunk). At start-up every `.open` segment
that a crash or power cut left behind is recovered into a readable `.mcap` holding each of its intact chunks
(segment_files.recover_unclosed); one with bytes that could not be read is also kept whole as `.mcap.damaged`
(quarantined), counted and reported in the health detail. A recorder the supervisor restarted then resumes each topic
after the last message that its daemon run's segments hold (`daemon_run` in their metadata, the highest seq per topic in
their closing metadata), so what was published while it was down, or torn off with the crash's unfinished chunk, is
recorded once, as long as the ring still holds it (older messages count as lost).
The disk policy (daemon/processes/disk_policy.py) deletes the oldest closed (or quarantined) segments to keep the
configured free space, one at a time and only while that frees space (not when another program takes it), never the
newest `recorder.keep_newest_s` of drive; what it deleted (segments, seconds of drive, bytes) is in the health detail
and the log. When that is not enough the recorder closes its segment, counts what it cannot write per topic, and resumes
once space returns. Messages written, lost to bus overtaking and dropped for lack of disk go per topic into each
segment's closing metadata and, as JSON, into the `detail` of the recorder's health. Once a second it publishes a
TimeAnchor (host monotonic + UTC), which it logs like any topic. What it reads goes through a reorder buffer
(reorder_buffer.py): held until no ring can still give an older message, at most `recorder.reorder_window_s` (live; a
replay's played topics have exact bounds and no window), then written oldest first, so each segment's chunks are in
log-time order; a message older than one already written is written at once and counted as late (`late_per_topic`). The
derived topics published seconds after the time they are stamped at (viewing clouds, fused poses: a Topic's
`stamp_lag_s`) go through a reorder buffer of their own, written in batches of LAGGING_BATCH_S in chunks of their own,
so they never hold the sensors' messages back: a power cut loses at most REORDER_SLACK_NS plus a sync period of what the
sensors sent, and the last few seconds of the derived topics (which `reconstruct` derives again). In a replay the played
topics run on the log's clock, behind this host's at a rate below 1, ahead of it above: a played ring read to its end
bounds what it can still give by the newest played message read (the player publishes in log-time order), and the topics
not played (the processes' health, on this host's clock) are ordered on their own.

The recorder is a normal (non-lossless) bus reader: one thread polls every subscriber in turn, so it can never slow a
driver down; if it falls behind a ring, it loses (and counts) the oldest messages. Only when the daemon replays a log as
fast as its consumers allow (`--lossless`, given by the process table for `replay --rate max`) does it register as a
lossless reader: the player then waits for it, as for the mapper, and the re-recorded log is complete.
"""

from __future__ import annotations

import argparse
import heapq
import json
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from daemon.bus import pubsub
from daemon.log_format.writer import LogWriter
from daemon.processes import disk_policy
from daemon.processes.reorder_buffer import ReorderBuffer
from daemon.processes.segment_clock import SegmentClock
from daemon.processes.segment_files import (
    OPEN_SUFFIX,
    anchored_utc_ns,
    check_output_dir,
    closed_name,
    daemon_run,
    drive_seconds,
    last_recorded_seqs,
    next_segment_index,
    oldest_first,
    recover_unclosed,
    segment_name,
)
from daemon.spine.config import CarConfig, load_config, reports_config_errors
from daemon.spine.health import HealthCounters
from daemon.spine.messages import TimeAnchor
from daemon.spine.process_logging import setup_logging
from daemon.spine.process_table import RESTARTS_ENV, played_topics
from daemon.spine.stop_signals import set_on_signals
from daemon.spine.topics import TIME_ANCHOR, health_topic, topic_table

PROCESS = "recorder"
HEALTH_PERIOD_S = 1.0
SYNC_PERIOD_S = 1.0  # the open segment's complete chunks reach the disk at least this often (power cuts)
DISK_CHECK_PERIOD_S = 0.5
DISK_CHECK_BYTES = 16 * 1024 * 1024
SUBSCRIBE_RETRY_S = 0.5
IDLE_SLEEP_S = 0.005
DRAIN_LIMIT_S = 10.0  # at stop: longest time spent writing what is still waiting in the rings
READ_BURST = 256  # most messages taken from one topic before the next topic gets its turn
REORDER_MAX_BYTES = 1024**3  # the reorder buffer never holds more (it releases its oldest early)
REORDER_SLACK_NS = 500_000_000  # how far a driver's host stamp may precede its publish (a ring read to its end)
LAGGING_BATCH_S = 2.0  # the derived topics stamped before they are published are written this much at a time
log = logging.getLogger(__name__)


@dataclass
class TopicTally:
    """Per-topic totals since the recorder started."""

    written: dict[str, int] = field(default_factory=dict)
    lost_bus: dict[str, int] = field(default_factory=dict)
    dropped_disk_full: dict[str, int] = field(default_factory=dict)

    def lost(self) -> dict[str, int]:
        topics = set(self.lost_bus) | set(self.dropped_disk_full)
        return {t: self.lost_bus.get(t, 0) + self.dropped_disk_full.get(t, 0) for t in sorted(topics)}


def _delta(now: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {t: n - before.get(t, 0) for t, n in sorted(now.items()) if n != before.get(t, 0)}


class Recorder:
    """The recorder's state: the open segment, the disk state and the per-topic tallies. `live`: the bus's host times
    are this host's clock (a replay's may run ahead of it)."""

    def __init__(self, config: CarConfig, output_dir: Path, config_path: str | Path | None = None, live: bool = True):
        self.config = config
        self.config_path = config_path
        self.rc = config.recorder
        self.output_dir = output_dir
        self.run = daemon_run()
        output_dir.mkdir(parents=True, exist_ok=True)
        self.health = HealthCounters(PROCESS)
        self.recovered: list[dict] = []
        self.recover()
        self.next_index = next_segment_index(output_dir)
        self.writer: LogWriter | None = None
        self.open_path: Path | None = None
        self.live = live
        self.clock = SegmentClock(self.rc.segment_seconds, time.monotonic_ns if live else None)
        self.clock_topics = played_topics(config)
        self.played_newest_ns: int | None = None  # the newest host time read of the clock topics
        self.anchor: tuple[int, int] | None = None  # the last time anchor written: (host_mono_ns, utc_ns)
        self.first_log_ns: int | None = None  # the open segment's first message's time on the log's clock
        self._sync_fd: int | None = None
        self._last_sync = 0.0
        self.segments_closed = 0
        self.deleter = disk_policy.SegmentDeleter(
            config.recorder.keep_newest_s, lambda: oldest_first(output_dir), drive_seconds, self.health.count_error,
            output_dir / disk_policy.STATE_FILE, config.recorder.deletion_hold_off_s)
        self._closed_bytes = 0  # bytes written to the segments this recorder closed or abandoned
        self.tally = TopicTally()
        self._at_last_close = TopicTally()
        # a replay's played topics wait until their rings' bounds (exact: the player publishes in log-time order)
        # pass them, with no window: at --rate max one ring read ahead released what another one behind still held
        self.reorder = ReorderBuffer(int(self.rc.reorder_window_s * 1e9) if live else None, REORDER_MAX_BYTES)
        self.read_positions: dict[str, int] = {}  # per topic, the host time of the last message read
        # per topic, how long before a ring is read its next message may be stamped (Topic.stamp_lag_s)
        self.stamp_slack_ns = {name: max(REORDER_SLACK_NS, int(t.stamp_lag_s * 1e9))
                               for name, t in topic_table(config).items()}
        # the topics stamped longer before they are published than a driver's message: ordered on their own; in a
        # replay also every topic not played (the processes' health, stamped on this host's clock while the played
        # ones run on the log's, ahead of it or behind it): each clock's messages ordered on their own
        self.lagging = {name for name, slack in self.stamp_slack_ns.items() if slack > REORDER_SLACK_NS}
        if not live:
            self.lagging |= set(self.stamp_slack_ns) - self.clock_topics
        self.reorder_lagging = ReorderBuffer(int(self.rc.reorder_window_s * 1e9) + max(self.stamp_slack_ns.values(),
                                             default=0), REORDER_MAX_BYTES // 4)
        self._lagging_released_ns: int | None = None  # the safe bound the last batch of them was written up to
        self._late_at_last_close: dict[str, int] = {}
        self.disk_full = False
        self.disk_free_bytes = 0
        self._bytes_at_disk_check = 0
        self._last_disk_check = 0.0
        self.check_disk(force=True)

    # --- segments ----------------------------------------------------------------------------

    def recover(self) -> None:
        """Recover the unclosed segments in the folder; a quarantined or unrecoverable one counts as an error."""
        for report in recover_unclosed(self.output_dir, self.config):
            self.recovered.append(report)
            if report["quarantined"]:
                self.health.count_error(f"quarantined {Path(report['quarantined']).name}: {report['error']}")
            elif report["to"] is None:
                self.health.count_error(f"cannot recover {Path(report['from']).name}: {report['error']}")

    def _open_segment(self) -> None:
        name = segment_name(time.time_ns(), self.next_index)
        self.next_index += 1
        self.open_path = self.output_dir / (name + OPEN_SUFFIX)
        try:
            self.writer = LogWriter(self.open_path, self.config, config_path=self.config_path,
                                    metadata={"daemon_run": self.run})
        except OSError:  # a full disk while writing its header: a file with no message is not kept
            self.open_path.unlink(missing_ok=True)
            self.open_path = None
            raise
        self._sync_fd = os.open(self.open_path, os.O_RDONLY)  # fsync through it: LogWriter keeps its file private
        self._last_sync = time.monotonic()
        self._bytes_at_disk_check = 0
        log.info("opened segment %s", self.open_path.name)

    def close_segment(self) -> Path | None:
        """Close the open segment (counts in its metadata), rename it to `.mcap`; its final path."""
        writer, path, first_log_ns = self.writer, self.open_path, self.first_log_ns
        if writer is None or path is None:
            return None
        self.writer, self.open_path, self.first_log_ns = None, None, None
        self._close_sync_fd()
        self._closed_bytes += writer.bytes_written_estimate
        lost_bus = _delta(self.tally.lost_bus, self._at_last_close.lost_bus)
        dropped = _delta(self.tally.dropped_disk_full, self._at_last_close.dropped_disk_full)
        lost = {t: lost_bus.get(t, 0) + dropped.get(t, 0) for t in sorted(set(lost_bus) | set(dropped))}
        late = _delta(self.late(), self._late_at_last_close)
        self._late_at_last_close = self.late()
        self._at_last_close = TopicTally(dict(self.tally.written), dict(self.tally.lost_bus),
                                         dict(self.tally.dropped_disk_full))
        try:
            clock = {name: json.dumps(counts) for name, counts in self.clock.take_segment_counts().items()}
            writer.close(extra_metadata={"lost_per_topic": json.dumps(lost),
                                         "lost_bus_per_topic": json.dumps(lost_bus),
                                         "dropped_disk_full_per_topic": json.dumps(dropped),
                                         "late_per_topic": json.dumps(late), **clock})
            final = path.with_name(closed_name(path.name, anchored_utc_ns(self.anchor, first_log_ns)))
            os.replace(path, final)
        except OSError as exc:  # the `.open` file stays; recover_unclosed turns it into a readable file
            self.health.count_error(f"closing {path.name}: {exc}")
            log.error("cannot close segment %s: %s", path, exc)
            return None
        self.segments_closed += 1
        log.info("closed segment %s as %s (%d messages)", path.name, final.name, sum(writer.counts.values()))
        return final

    def sync_if_due(self) -> None:
        """Finish the open segment's chunk in progress and push it to the disk, so a power cut loses at most a
        second of what was written (and what the reorder buffer still held)."""
        if self.writer is None or time.monotonic() - self._last_sync < SYNC_PERIOD_S:
            return
        self._last_sync = time.monotonic()
        try:
            self.writer.flush()
            os.fsync(self._sync_fd)
        except OSError as exc:
            self.health.count_error(f"syncing {self.open_path.name}: {exc}")

    def _close_sync_fd(self) -> None:
        if self._sync_fd is not None:
            os.close(self._sync_fd)
            self._sync_fd = None

    # --- disk ----------------------------------------------------------------------------------

    def _own_bytes(self) -> int:
        """Bytes this recorder has written (uncompressed: at least what its segments took on the disk)."""
        return self._closed_bytes + (self.writer.bytes_written_estimate if self.writer else 0)

    def _make_room(self) -> tuple[int, int]:
        """Let the disk policy delete toward the required free space: (free, required) bytes."""
        usage = disk_policy.disk_usage(self.output_dir)
        required = disk_policy.required_free_bytes(usage.total_bytes, self.rc.min_free_gib, self.rc.min_free_pct)
        return self.deleter.make_room(usage, required, self._own_bytes()), required

    def check_disk(self, force: bool = False) -> None:
        """Apply the disk policy (at most every DISK_CHECK_PERIOD_S or DISK_CHECK_BYTES); stop or resume."""
        written = self.writer.bytes_written_estimate if self.writer else 0
        now = time.monotonic()
        if not force and now - self._last_disk_check < DISK_CHECK_PERIOD_S and \
                written - self._bytes_at_disk_check < DISK_CHECK_BYTES:
            return
        self._last_disk_check, self._bytes_at_disk_check = now, written
        free, required = self._make_room()
        if free < required and self.deleter.judging:  # deletions being judged: more may follow
            self.disk_free_bytes = free  # (writing goes on, or stays stopped, until then)
            return
        if free < required and self.writer is not None:
            self.close_segment()  # the open segment may be what fills the disk: let the policy weigh it too
            free, required = self._make_room()
        self.disk_free_bytes = free
        full = free < required
        if full and not self.disk_full:
            log.error("disk full: %d bytes free, %d required; writing stops until space returns", free, required)
            self.disk_full = True
        elif not full and self.disk_full:
            log.warning("disk space is back (%d bytes free): writing resumes", free)
            self.disk_full = False
            self.recover()

    # --- messages ------------------------------------------------------------------------------

    def accept(self, topic: str, message: object) -> None:
        """Take one message read from the bus: into its reorder buffer, or written at once when it is late."""
        buffer = self.reorder_lagging if topic in self.lagging else self.reorder
        if self.rc.reorder_window_s <= 0 or not buffer.push(topic, message):
            self.write(topic, message)

    def release(self, safe_ns: int | None = None, lagging_safe_ns: int | None = None) -> None:
        """Write what the reorder buffers may give: the sensors' messages up to `safe_ns`, the lagging topics' up to
        `lagging_safe_ns` once it is LAGGING_BATCH_S past their last batch."""
        for topic, message in self.reorder.pop_ready(safe_ns):
            self.write(topic, message)
        if not len(self.reorder_lagging):
            return
        batch_due = lagging_safe_ns is not None and (
            self._lagging_released_ns is None or lagging_safe_ns - self._lagging_released_ns >= LAGGING_BATCH_S * 1e9)
        if batch_due or self.reorder_lagging.bytes_held > self.reorder_lagging.max_bytes:
            self._lagging_released_ns = lagging_safe_ns
            for topic, message in self.reorder_lagging.pop_ready(lagging_safe_ns):
                self.write(topic, message)

    def release_everything(self) -> None:
        """Write all that both reorder buffers hold, oldest first (at stop)."""
        for topic, message in heapq.merge(self.reorder.drain(), self.reorder_lagging.drain(),
                                          key=lambda held: int(held[1].host_mono_ns)):
            self.write(topic, message)

    def late(self) -> dict[str, int]:
        """Per topic, the messages written older than one of their own order written before them."""
        late = dict(self.reorder.late)
        for topic, n in self.reorder_lagging.late.items():
            late[topic] = late.get(topic, 0) + n
        return dict(sorted(late.items()))

    def write(self, topic: str, message: object) -> None:
        """Write one message to the open segment (opening one if none is), or count it as dropped."""
        if topic in self.clock_topics and self.clock.begins_segment(topic, int(message.host_mono_ns)) and \
                self.writer is not None:
            self.close_segment()
            self.check_disk(force=True)
        if topic == TIME_ANCHOR and message.utc_ns > 0:
            self.anchor = (int(message.host_mono_ns), int(message.utc_ns))
        if self.disk_full:
            self.tally.dropped_disk_full[topic] = self.tally.dropped_disk_full.get(topic, 0) + 1
            return
        try:
            if self.writer is None:
                self._open_segment()
            self.writer.write(topic, message)
            if self.first_log_ns is None and (self.live or topic in self.clock_topics):  # not played: host clock
                self.first_log_ns = int(message.host_mono_ns)
        except OSError as exc:  # ENOSPC and the like: stop and let the disk check decide when to go on
            self.health.count_error(f"writing {topic}: {exc}")
            log.error("write failed on %s: %s", self.open_path or self.output_dir, exc)
            self.tally.dropped_disk_full[topic] = self.tally.dropped_disk_full.get(topic, 0) + 1
            self.disk_full = True
            if self.writer is not None:
                self._abandon_segment()
            return
        self.tally.written[topic] = self.tally.written.get(topic, 0) + 1
        self.health.count_published()
        if self.writer.bytes_written_estimate >= self.rc.segment_bytes:
            self.close_segment()
            self.check_disk(force=True)

    def _abandon_segment(self) -> None:
        """Drop a segment that could not be written; its `.open` file is recovered when space returns."""
        self._closed_bytes += self.writer.bytes_written_estimate
        self.writer, self.open_path, self.first_log_ns = None, None, None
        self._close_sync_fd()

    def set_lost(self, topic: str, lost: int) -> None:
        """The subscriber's running count of messages the bus overwrote before the recorder read them."""
        if lost:
            self.tally.lost_bus[topic] = lost

    def health_message(self):
        msg = self.health.snapshot()
        lost = self.tally.lost()
        msg.dropped = sum(lost.values())
        msg.state = "error" if self.disk_full else ("degraded" if msg.errors else "ok")
        msg.detail = json.dumps({
            "segment": str(self.open_path) if self.open_path else None,
            "segments_closed": self.segments_closed,
            "segments_deleted": self.deleter.segments,
            "disk_policy": self.deleter.report(),
            "disk_free_bytes": self.disk_free_bytes,
            "disk_full": self.disk_full,
            "written": dict(sorted(self.tally.written.items())),
            "lost": lost,
            "lost_bus": dict(sorted(self.tally.lost_bus.items())),
            "dropped_disk_full": dict(sorted(self.tally.dropped_disk_full.items())),
            "late": self.late(),
            "segment_clock": self.clock.report(),
            "reorder_held": len(self.reorder) + len(self.reorder_lagging),
            "recovered": self.recovered,
            "segments_quarantined": sum(1 for r in self.recovered if r["quarantined"]),
            "last_error": self.health.last_error,
        })
        return msg


def logged_topics(config: CarConfig) -> list[str]:
    return sorted(name for name, t in topic_table(config).items() if t.logged)


def _read_round(rec: Recorder, subscribers: dict[str, pubsub.Subscriber]) -> int:
    """Take what each subscriber has waiting (at most READ_BURST per topic), write what the reorder buffers then
    release; the number read. No ring can still give a message older than its bound: a ring read to its end gives
    nothing stamped before the time it was read (less REORDER_SLACK_NS, or its topic's stamp lag) or its last message
    (a replay's host times may lie ahead), in a replay a played ring nothing before the newest played message read
    (the player publishes in log-time order), one the recorder is behind on nothing before its last message. The
    sensors' messages are released up to the lowest bound of their rings, the lagging topics' up to theirs."""
    got = 0
    safe: dict[bool, int] = {}  # is the topic lagging -> the lowest bound of those rings
    for topic, sub in subscribers.items():
        read_at = time.monotonic_ns()
        drained = False
        for _ in range(READ_BURST):
            msg = sub.read(timeout_s=0, copy=True)
            if msg is None:
                drained = True
                break
            rec.accept(topic, msg)
            rec.read_positions[topic] = int(msg.host_mono_ns)
            if topic in rec.clock_topics:
                rec.played_newest_ns = max(rec.played_newest_ns or 0, int(msg.host_mono_ns))
            got += 1
        rec.set_lost(topic, sub.lost)
        position = rec.read_positions.get(topic)
        slack = rec.stamp_slack_ns.get(topic, REORDER_SLACK_NS)
        if drained and not rec.live and topic in rec.clock_topics:
            # a replay publishes these in log-time order, on the log's clock (behind this host's at a rate below 1):
            # what this ring gives later was published after, so stamped no earlier than, all read of them so far
            bound = max(rec.played_newest_ns or 0, position or 0) or None
        else:
            bound = max(read_at - slack, position or 0) if drained else position
        if bound is not None:
            lagging = topic in rec.lagging
            safe[lagging] = min(safe.get(lagging, bound), bound)
    rec.release(safe.get(False), safe.get(True))
    return got


def run(config: CarConfig, output_dir: Path, stop: threading.Event, config_path: str | Path | None = None,
        time_anchors: bool = True, lossless: bool = False) -> Recorder:
    """Record until `stop` is set, then write what is still waiting in the rings and close the segment."""
    rec = Recorder(config, output_dir, config_path, live=time_anchors)  # the live recorder stamps the anchors
    # in replay mode the log player publishes the recorded anchors instead
    anchor_pub = pubsub.open_publisher(config, TIME_ANCHOR) if time_anchors else None
    health_pub = pubsub.open_publisher(config, health_topic(PROCESS))
    wanted = logged_topics(config)
    subscribers: dict[str, pubsub.Subscriber] = {}
    # First start in a daemon run: everything in the rings (the daemon made them empty before starting its
    # processes). After a restart: from the message after the last one this run's segments hold (recovered
    # from the crash), so what was published while it was down is recorded as long as the ring still holds
    # it (what it no longer holds is counted lost). Topics that appear later: from their first message.
    resume = last_recorded_seqs(output_dir, rec.run) if int(os.environ.get(RESTARTS_ENV, "0")) > 0 else {}
    if resume:
        log.info("restarted: resuming after the last recorded seq of %d topics", len(resume))
    last_subscribe = last_health = 0.0
    try:
        while not stop.is_set():
            now = time.monotonic()
            if len(subscribers) < len(wanted) and now - last_subscribe >= SUBSCRIBE_RETRY_S:
                last_subscribe = now
                for topic in wanted:
                    if topic not in subscribers:
                        try:
                            subscribers[topic] = pubsub.open_subscriber(config, topic, start="oldest",
                                                                     lossless=lossless, after_seq=resume.get(topic))
                        except FileNotFoundError:
                            pass
            if now - last_health >= HEALTH_PERIOD_S:
                last_health = now
                mono, utc = time.monotonic_ns(), time.time_ns()
                if anchor_pub is not None:
                    anchor_pub.publish(TimeAnchor(sensor_time_ns=mono, host_mono_ns=mono, utc_ns=utc))
                health_pub.publish(rec.health_message())
            got = _read_round(rec, subscribers)
            rec.sync_if_due()
            rec.check_disk()
            if not got:
                stop.wait(IDLE_SLEEP_S)
        drain_until = time.monotonic() + DRAIN_LIMIT_S
        while _read_round(rec, subscribers) and time.monotonic() < drain_until:
            pass
    finally:
        rec.release_everything()
        rec.close_segment()
        health_pub.publish(rec.health_message())
        for sub in subscribers.values():
            sub.close()
        if anchor_pub is not None:
            anchor_pub.close()
        health_pub.close()
    return rec


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog recorder", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--output-dir", help="folder for the segments (default: recorder.output_dir)")
    parser.add_argument("--no-time-anchors", action="store_true",
                        help="do not publish monotonic/UTC anchors (replay: the player publishes the recorded ones, "
                             "and its host times may run ahead of this host's clock)")
    parser.add_argument("--lossless", action="store_true",
                        help="read losslessly: publishers wait for the recorder (replay at max speed only)")
    args = parser.parse_args(argv)
    setup_logging("recorder")
    config = load_config(args.config)
    output_dir = check_output_dir(config, args.config, args.output_dir)
    stop = threading.Event()
    set_on_signals(stop)
    rec = run(config, output_dir, stop, args.config, time_anchors=not args.no_time_anchors, lossless=args.lossless)
    log.info("stopped: %d segments closed, %d messages written, %d lost; disk policy deleted %d segments "
             "(%.1f s of drive, %d bytes)", rec.segments_closed, sum(rec.tally.written.values()),
             sum(rec.tally.lost().values()), rec.deleter.segments, rec.deleter.seconds, rec.deleter.bytes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
