"""Reading: `read_log` iterates chosen topics of several files in log-time order; a truncated file (a writer killed
mid-write) is read up to its last complete chunk and the bytes skipped are reported in a `ReadReport`."""

from __future__ import annotations

import heapq
import io
import logging
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary

from daemon.log_format.foxglove_schemas import FROM_WELL_KNOWN, TYPE_OF_FOREIGN_SCHEMA
from daemon.spine import message_codec
from daemon.spine.messages import MESSAGE_TYPE_BY_NAME

log = logging.getLogger(__name__)


@dataclass(slots=True)
class LogRecord:
    topic: str
    message: object
    log_time_ns: int
    path: Path


@dataclass
class FileReport:
    path: Path
    complete: bool = True
    messages: int = 0
    bytes_total: int = 0
    bytes_skipped: int = 0
    undecodable: int = 0
    error: str = ""


@dataclass
class ReadReport:
    """What `read_log` met in each file: truncation, bytes skipped, messages it could not decode."""

    files: list[FileReport] = field(default_factory=list)

    @property
    def bytes_skipped(self) -> int:
        return sum(f.bytes_skipped for f in self.files)

    @property
    def incomplete_files(self) -> list[Path]:
        return [f.path for f in self.files if not f.complete]


MCAP_MAGIC = b"\x89MCAP0\r\n"


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
    return f"{path} is not an MCAP file"


def decode_record(schema: Schema | None, channel: Channel, message: Message) -> object | None:
    """The message dataclass of one MCAP message, or None for channels that are not roadlog topics (a channel of
    another tool's log is one when its schema can only be one roadlog message: TYPE_OF_FOREIGN_SCHEMA)."""
    type_name = channel.metadata.get("roadlog.type") or TYPE_OF_FOREIGN_SCHEMA.get(schema.name if schema else "", "")
    msg_type = MESSAGE_TYPE_BY_NAME.get(type_name)
    if msg_type is None or schema is None:
        return None
    adapter = FROM_WELL_KNOWN.get((type_name, schema.name))
    if adapter is not None:
        cls, from_proto = adapter
        proto = cls()
        proto.ParseFromString(message.data)
        return from_proto(proto, message.sequence, message.log_time)
    if schema.name == message_codec.schema_name(msg_type):
        return message_codec.decode(msg_type, message.data)
    return None


def _iter_complete_file(path: Path, summary: Summary, topics: set[str] | None, start_ns, end_ns):
    """Messages of a closed file in log-time order: chunks taken by start time, each chunk's messages
    released once no later chunk can hold an earlier one (a plain tuple heap: cheaper than mcap's own)."""
    with open(path, "rb") as f:
        chunks = sorted((c for c in summary.chunk_indexes
                         if (start_ns is None or c.message_end_time >= start_ns)
                         and (end_ns is None or c.message_start_time < end_ns)),
                        key=lambda c: (c.message_start_time, c.chunk_start_offset))
        wanted = {cid for cid, ch in summary.channels.items() if topics is None or ch.topic in topics}
        heap: list = []
        counter = 0
        for k, index in enumerate(chunks):
            f.seek(index.chunk_start_offset + 1 + 8)
            for record in breakup_chunk(Chunk.read(ReadDataStream(f))):
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


def _iter_truncated_file(path: Path, report: FileReport, topics: set[str] | None, start_ns, end_ns,
                         reorder_window: int = 20000):
    """Stream the complete records of a damaged file, re-ordered by log time within a window."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    heap: list = []
    counter = 0
    with open(path, "rb") as f:
        reader = StreamReader(f, record_size_limit=1 << 31)
        good_offset = 0
        try:
            for record in reader.records:
                good_offset = f.tell()
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None or (topics is not None and channel.topic not in topics):
                        continue
                    if (start_ns is not None and record.log_time < start_ns) or (
                            end_ns is not None and record.log_time >= end_ns):
                        continue
                    heapq.heappush(heap, (record.log_time, counter, schemas.get(channel.schema_id), channel, record))
                    counter += 1
                    if len(heap) > reorder_window:
                        yield heapq.heappop(heap)[2:]
        except (McapError, EOFError, ValueError, OSError, KeyError, struct.error) as exc:
            report.complete = False
            report.error = f"{type(exc).__name__}: {exc}"
        report.bytes_skipped = max(0, report.bytes_total - good_offset) if not report.complete else 0
    while heap:
        yield heapq.heappop(heap)[2:]


def _closed_file_summary(path: Path) -> Summary | None:
    """The summary of a file that ends with a valid footer (it was closed properly), else None."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
            f.seek(-8, io.SEEK_END)
            return summary if f.read(8) == b"\x89MCAP0\r\n" else None
    except Exception:  # noqa: BLE001 - any failure means "read it the careful way"
        return None


def _iter_file(path: Path, report: FileReport, topics, start_ns, end_ns) -> Iterator[LogRecord]:
    report.bytes_total = path.stat().st_size
    summary = _closed_file_summary(path)
    if summary is not None:
        source = _iter_complete_file(path, summary, topics, start_ns, end_ns)
    else:
        report.complete = False
        source = _iter_truncated_file(path, report, topics, start_ns, end_ns)
    for schema, channel, message in source:
        try:
            decoded = decode_record(schema, channel, message)
        except Exception:  # noqa: BLE001 - a corrupt message is counted, not fatal
            report.undecodable += 1
            continue
        if decoded is None:
            continue
        report.messages += 1
        yield LogRecord(channel.topic, decoded, message.log_time, path)
    if not report.complete:
        log.warning("%s: truncated log, read up to the last complete chunk, skipped %d of %d bytes (%s)",
                    path, report.bytes_skipped, report.bytes_total, report.error or "no footer")


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
    """The metadata records of one file (name -> key/value), also from a truncated file (scanned, up to the
    record named `until` if given: the writer puts METADATA_NAME first; a closed file's are found through
    its summary)."""
    out: dict[str, dict[str, str]] = {}
    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - no footer: a truncated file
            summary = None
        if summary is not None and summary.metadata_indexes:
            for index in summary.metadata_indexes:
                f.seek(index.offset)
                record = next(StreamReader(f, skip_magic=True, record_size_limit=1 << 31).records)
                out[record.name] = dict(record.metadata)
            return out
        f.seek(0)
        try:
            for record in StreamReader(f, record_size_limit=1 << 31).records:
                if type(record).__name__ == "Metadata":
                    out[record.name] = dict(record.metadata)
                    if record.name == until:
                        break
        except Exception:  # noqa: BLE001 - a truncated tail just ends the scan
            pass
    return out
