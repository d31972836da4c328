"""Reading: `read_log` iterates chosen topics of several files in log-time order. Every chunk is checked against its
CRC; a closed file is read through its summary (when that matches the footer's CRC), any other file (a writer killed
mid-write, a power cut, damage) record by record past its damaged stretches (record_scan). What was skipped, and why,
is reported per file in a `ReadReport`; a damaged file never raises. Times given and returned are host monotonic:
a UTC log time is moved back by its channel's offset (metadata_records.log_time_offset), an older log's is as it is."""

from __future__ import annotations

import heapq
import logging
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.records import Channel, Message, Metadata, Schema
from mcap.summary import Summary

from daemon.log_format.foxglove_schemas import FROM_WELL_KNOWN, TYPE_OF_FOREIGN_SCHEMA
from daemon.log_format.metadata_records import CHANNEL_METADATA_NAME, channel_from_record, log_time_offset
from daemon.log_format.record_scan import (
    Damage,
    DamagedRecord,
    check_closed_file,
    read_chunk_at,
    read_record_at,
    resync,
    scan_records,
    trusted_summary,
)
from daemon.spine import message_codec
from daemon.spine.messages import MESSAGE_TYPE_BY_NAME

log = logging.getLogger(__name__)


@dataclass(slots=True)
class LogRecord:
    topic: str
    message: object
    log_time_ns: int  # host monotonic: the message's host_mono_ns (the MCAP log time less its file's UTC offset)
    path: Path


@dataclass
class FileReport:
    """One file as read: complete = closed and every byte of it read; otherwise `error` says what was met first."""

    path: Path
    complete: bool = True
    messages: int = 0
    bytes_total: int = 0
    bytes_skipped: int = 0  # bytes that could not be read (damaged stretches, a truncated end)
    damaged_chunks: int = 0  # damaged stretches skipped: a chunk that failed its CRC or decompression, garbage
    undecodable: int = 0  # messages read but not decoded (a bad payload, their channel lost with a damaged chunk)
    error: str = ""
    damage: Damage = field(default_factory=Damage, repr=False)

    def settle(self) -> None:
        """Fold what the walk met (`damage`) into the report."""
        self.bytes_skipped, self.damaged_chunks = self.damage.bytes_skipped, self.damage.stretches
        if self.damage.bytes_skipped or self.damage.stretches or self.damage.first_error:
            self.complete = False
            self.error = "; ".join(e for e in (self.error, self.damage.first_error) if e)


@dataclass
class ReadReport:
    """What `read_log` met in each file: truncation, damage, bytes skipped, messages it could not decode."""

    files: list[FileReport] = field(default_factory=list)

    @property
    def bytes_skipped(self) -> int:
        return sum(f.bytes_skipped for f in self.files)

    @property
    def incomplete_files(self) -> list[Path]:
        return [f.path for f in self.files if not f.complete]


MCAP_MAGIC = b"\x89MCAP0\r\n"
MAGICLESS_SCAN_BYTES = 64 * 1024 * 1024  # how far a file without the magic is searched for an intact MCAP record


def not_a_log(path: str | Path) -> str | None:
    """Why `path` cannot be read as a roadlog log (None: it is an MCAP file), naming what it looks like instead."""
    path = Path(path)
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return f"{path} is a ROS 2 bag: import it first (roadlog import ros2 {path} --out LOG.mcap)"
        return f"{path} is a folder, not an MCAP log"
    if not path.is_file():
        return f"{path}: no such file"
    with open(path, "rb") as f:
        head = f.read(16)
        if head.startswith(MCAP_MAGIC):
            return None
        if head.startswith(b"SQLite format 3"):
            return f"{path} is a ROS 2 bag's sqlite3 storage: import its bag folder first (roadlog import ros2)"
        if resync(f, 0, min(os.fstat(f.fileno()).st_size, MAGICLESS_SCAN_BYTES)) is not None:
            return None  # an MCAP file whose first block was torn: read_log reads what is intact and says so
    return f"{path} is not an MCAP file"


def decode_record(schema: Schema | None, channel: Channel, message: Message, host_ns: int | None = None
                  ) -> object | None:
    """The message dataclass of one MCAP message (host_mono_ns = `host_ns`, default its log time), or None for
    channels that are not roadlog topics (a channel of another tool's log is one when its schema can only be one
    roadlog message: TYPE_OF_FOREIGN_SCHEMA)."""
    type_name = channel.metadata.get("roadlog.type") or TYPE_OF_FOREIGN_SCHEMA.get(schema.name if schema else "", "")
    msg_type = MESSAGE_TYPE_BY_NAME.get(type_name)
    if msg_type is None or schema is None:
        return None
    adapter = FROM_WELL_KNOWN.get((type_name, schema.name))
    if adapter is not None:
        cls, from_proto = adapter
        proto = cls()
        proto.ParseFromString(message.data)
        return from_proto(proto, message.sequence, message.log_time if host_ns is None else host_ns)
    if schema.name == message_codec.schema_name(msg_type):
        return message_codec.decode(msg_type, message.data)
    return None


def _iter_complete_file(f: BinaryIO, summary: Summary, report: FileReport, topics: set[str] | None, start_ns,
                        end_ns):
    """Messages of a closed file in log-time order: chunks taken by start time, each chunk's messages
    released once no later chunk can hold an earlier one (a plain tuple heap: cheaper than mcap's own). A chunk
    that fails its CRC or does not decompress is skipped and counted."""
    wanted = {cid: log_time_offset(ch.metadata) for cid, ch in summary.channels.items()
              if topics is None or ch.topic in topics}
    offset = max(wanted.values(), default=0)  # the file's (every channel of a roadlog file has the same)
    start_ns = None if start_ns is None else start_ns + offset
    end_ns = None if end_ns is None else end_ns + offset
    chunks = sorted((c for c in summary.chunk_indexes
                     if (start_ns is None or c.message_end_time >= start_ns)
                     and (end_ns is None or c.message_start_time < end_ns)),
                    key=lambda c: (c.message_start_time, c.chunk_start_offset))
    heap: list = []
    counter = 0
    for k, index in enumerate(chunks):
        try:
            records = read_chunk_at(f, index.chunk_start_offset, index.chunk_length)
        except DamagedRecord as exc:
            report.damage.skip(index.chunk_start_offset, index.chunk_length, str(exc))
            records = []
        for record in records:
            if not isinstance(record, Message) or record.channel_id not in wanted:
                continue
            if (start_ns is not None and record.log_time < start_ns) or (
                    end_ns is not None and record.log_time >= end_ns):
                continue
            heapq.heappush(heap, (record.log_time, counter, record))
            counter += 1
        release_before = chunks[k + 1].message_start_time if k + 1 < len(chunks) else None
        while heap and (release_before is None or heap[0][0] < release_before):
            record = heapq.heappop(heap)[2]
            channel = summary.channels[record.channel_id]
            yield summary.schemas.get(channel.schema_id), channel, record


def _iter_scanned_file(f: BinaryIO, report: FileReport, topics: set[str] | None, start_ns, end_ns,
                       reorder_window: int = 20000):
    """Every intact message of a file without a trusted summary (never closed, or damaged), re-ordered by host time
    within a window; damaged stretches are skipped (record_scan) and counted, as are messages whose channel
    was lost with them."""
    schemas: dict[int, Schema] = {}
    offsets: dict[int, int] = {}
    channels: dict[int, Channel] = {}
    heap: list = []
    counter = 0
    for record in scan_records(f, report.bytes_total, report.damage):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Metadata) and record.name == CHANNEL_METADATA_NAME:
            described = channel_from_record(record.metadata)
            if described is not None:
                channels.setdefault(described[0].id, described[0])
                schemas.setdefault(described[1].id, described[1])
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                report.undecodable += 1
                continue
            if topics is not None and channel.topic not in topics:
                continue
            offset = offsets.get(record.channel_id)
            if offset is None:
                offset = offsets[record.channel_id] = log_time_offset(channel.metadata)
            host_ns = record.log_time - offset
            if (start_ns is not None and host_ns < start_ns) or (end_ns is not None and host_ns >= end_ns):
                continue
            heapq.heappush(heap, (host_ns, counter, schemas.get(channel.schema_id), channel, record))
            counter += 1
            if len(heap) > reorder_window:
                yield heapq.heappop(heap)[2:]
    while heap:
        yield heapq.heappop(heap)[2:]


def _iter_file(path: Path, report: FileReport, topics, start_ns, end_ns) -> Iterator[LogRecord]:
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed below, also when the consumer stops early
    except OSError as exc:
        report.complete, report.error = False, f"cannot open: {exc.strerror}"
        log.error("%s: %s", path, report.error)
        return
    try:
        report.bytes_total = os.fstat(f.fileno()).st_size
        summary, why = trusted_summary(f, report.bytes_total)
        if summary is not None:
            check_closed_file(f, summary, report.damage)
            source = _iter_complete_file(f, summary, report, topics, start_ns, end_ns)
        else:
            report.complete, report.error = False, why
            source = _iter_scanned_file(f, report, topics, start_ns, end_ns)
        offsets: dict[int, int] = {}
        for schema, channel, message in source:
            offset = offsets.get(message.channel_id)
            if offset is None:
                offset = offsets[message.channel_id] = log_time_offset(channel.metadata)
            try:
                decoded = decode_record(schema, channel, message, message.log_time - offset)
            except Exception:  # noqa: BLE001 - a corrupt message is counted, not fatal
                report.undecodable += 1
                continue
            if decoded is None:
                continue
            report.messages += 1
            yield LogRecord(channel.topic, decoded, message.log_time - offset, path)
    except OSError as exc:  # a disk read error: what came before stands, the rest of the file is lost
        report.damage.skip(0, 0, f"read error: {exc.strerror}")
    finally:
        f.close()
    report.settle()
    if report.damage.stretches:
        log.error("%s: damaged log: %d damaged stretches skipped, %d of %d bytes unread (%s)", path,
                  report.damage.stretches, report.bytes_skipped, report.bytes_total, report.error)
    elif report.bytes_skipped:
        log.warning("%s: truncated log, read up to its last complete record, skipped %d of %d bytes (%s)",
                    path, report.bytes_skipped, report.bytes_total, report.error)
    elif not report.complete:
        log.warning("%s: unclosed log (%s), read record by record, nothing skipped", path,
                    report.error or "no footer")


def read_log(paths: Iterable[str | Path] | str | Path, topics: Iterable[str] | None = None,
             start_ns: int | None = None, end_ns: int | None = None,
             report: ReadReport | None = None) -> Iterator[LogRecord]:
    """Messages of the chosen topics from one or more MCAP files, merged in log-time order."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    topic_set = set(topics) if topics is not None else None
    report = report if report is not None else ReadReport()
    iterators = []
    for p in sorted(Path(x) for x in paths):
        fr = FileReport(Path(p))
        report.files.append(fr)
        iterators.append(_iter_file(Path(p), fr, topic_set, start_ns, end_ns))
    yield from heapq.merge(*iterators, key=lambda r: r.log_time_ns)


def read_metadata(path: str | Path, until: str | None = None) -> dict[str, dict[str, str]]:
    """The metadata records of one file (name -> key/value), also from a truncated or damaged file (scanned, up to
    the record named `until` if given: the writer puts METADATA_NAME first; a closed file's are found through its
    summary). The per-channel records (CHANNEL_METADATA_NAME) are the reader's own and are left out."""
    out: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            summary, _ = trusted_summary(f, size)
            if summary is not None:
                for index in summary.metadata_indexes:
                    if index.name == CHANNEL_METADATA_NAME:
                        continue
                    try:
                        record = read_record_at(f, index.offset, index.length)
                    except DamagedRecord:
                        continue
                    if isinstance(record, Metadata):
                        out[record.name] = dict(record.metadata)
                return out
            for record in scan_records(f, size, Damage(), chunks=False):
                if isinstance(record, Metadata) and record.name != CHANNEL_METADATA_NAME:
                    out[record.name] = dict(record.metadata)
                    if record.name == until:
                        break
    except OSError:  # unreadable: no metadata
        pass
    return out


def summary_message_count(paths: Iterable[str | Path], topics: Iterable[str]) -> int | None:
    """How many messages of `topics` the files' (trusted) summaries count: what read_log will give, for a progress
    bar; None when a file has none (never closed, damaged: only reading it tells)."""
    wanted, total = set(topics), 0
    for path in paths:
        with open(path, "rb") as f:
            summary, _ = trusted_summary(f, os.fstat(f.fileno()).st_size)
        if summary is None or summary.statistics is None:
            return None
        counts = summary.statistics.channel_message_counts
        total += sum(counts.get(cid, 0) for cid, ch in summary.channels.items() if ch.topic in wanted)
    return total


def last_log_time(path: str | Path) -> int | None:
    """The file's last log time from its (trusted) summary, on the host's monotonic clock like every time read_log
    gives; None for a file without one."""
    try:
        with open(path, "rb") as f:
            summary, _ = trusted_summary(f, os.fstat(f.fileno()).st_size)
    except OSError:
        return None
    stats = summary.statistics if summary is not None else None
    if stats is None:
        return None
    return stats.message_end_time - max((log_time_offset(ch.metadata) for ch in summary.channels.values()), default=0)


def summary_message_counts(path: str | Path) -> dict[str, int] | None:
    """Messages per topic from a closed file's (trusted) summary statistics, without reading a message; None for a
    file without one (open, torn or damaged: read it with read_log instead)."""
    try:
        with open(path, "rb") as f:
            summary, _ = trusted_summary(f, os.fstat(f.fileno()).st_size)
    except OSError:
        return None
    if summary is None or summary.statistics is None:
        return None
    counts: dict[str, int] = {}
    for channel_id, n in summary.statistics.channel_message_counts.items():
        channel = summary.channels.get(channel_id)
        if channel is not None:
            counts[channel.topic] = counts.get(channel.topic, 0) + n
    return counts
