"""The log format: MCAP files, one channel per topic, protobuf schemas Foxglove can open.

Writing: `LogWriter` maps camera frames, masks, GNSS fixes and poses to Foxglove's well-known schemas
(CompressedImage / CompressedVideo / RawImage, LocationFix, PoseInFrame) and every other message to
its `roadlog.<Name>` schema derived from `daemon.spine.messages`. Each MCAP message record carries
sequence = the message's per-topic seq, log_time = host_mono_ns and publish_time = sensor_time_ns, so
every field round-trips. Each file starts with a `roadlog` metadata record (software version, resolved
config, calibration, host, start time) and holds a CameraCalibration channel per camera.

Reading: `read_log` iterates chosen topics of several files in log-time order; a truncated file (a
writer killed mid-write) is read up to its last complete chunk and the bytes skipped are reported.
See docs/log-format.md.
"""

from __future__ import annotations

import heapq
import io
import json
import logging
import os
import socket
import struct
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary
from mcap.writer import CompressionType, Writer

from daemon.spine import message_codec
from daemon.spine.config import CarConfig, config_to_yaml, resolve_path
from daemon.spine.messages import MESSAGE_TYPE_BY_NAME, CameraFrame, GnssFix, SemanticMask, VehiclePose
from daemon.spine.topics import calibration_topic, topic_table

SOFTWARE_VERSION = "roadlog 0.1.0"
METADATA_NAME = "roadlog"
COUNTS_METADATA_NAME = "roadlog.counts"
_RAW_FORMATS = {"rgb8": 3, "bgr8": 3, "mono8": 1}
_VIDEO_FORMATS = {"h264", "h265"}
log = logging.getLogger(__name__)


def _file_descriptor_set(file_descriptor: FileDescriptor) -> bytes:
    """The FileDescriptorSet of a compiled protobuf file and everything it imports."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(file_descriptor)
    return fds.SerializeToString()


def _set_time(stamp, ns: int) -> None:
    stamp.seconds, stamp.nanos = divmod(int(ns), 1_000_000_000)


def _get_time(stamp) -> int:
    return stamp.seconds * 1_000_000_000 + stamp.nanos


# --- well-known schema adapters: (schema name, protobuf class, to_proto, from_proto) -------------

def _frame_schema(msg: CameraFrame) -> type:
    if msg.format in _RAW_FORMATS:
        return RawImage
    return CompressedVideo if msg.format in _VIDEO_FORMATS else CompressedImage


def _camera_to_proto(msg: CameraFrame):
    cls = _frame_schema(msg)
    proto = cls(frame_id=msg.camera, data=bytes(msg.data))
    _set_time(proto.timestamp, msg.sensor_time_ns)
    if cls is RawImage:
        proto.width, proto.height, proto.encoding = msg.width, msg.height, msg.format
        proto.step = msg.width * _RAW_FORMATS[msg.format]
    else:
        proto.format = msg.format
    return proto


def _camera_from_proto(proto, seq: int, log_time: int) -> CameraFrame:
    if isinstance(proto, RawImage):
        fmt, width, height = proto.encoding, proto.width, proto.height
    else:
        fmt, width, height = proto.format, 0, 0
    return CameraFrame(seq, _get_time(proto.timestamp), log_time, proto.frame_id, fmt, width, height, proto.data)


def _mask_to_proto(msg: SemanticMask) -> CompressedImage:
    proto = CompressedImage(frame_id=msg.camera, data=bytes(msg.data), format=msg.format)
    _set_time(proto.timestamp, msg.sensor_time_ns)
    return proto


def _mask_from_proto(proto, seq: int, log_time: int) -> SemanticMask:
    return SemanticMask(seq, _get_time(proto.timestamp), log_time, proto.frame_id, proto.format, proto.data)


def _fix_to_proto(msg: GnssFix) -> LocationFix:
    proto = LocationFix(
        frame_id="gnss",
        latitude=msg.latitude_deg,
        longitude=msg.longitude_deg,
        altitude=msg.altitude_m,
        position_covariance=list(msg.position_covariance),
        position_covariance_type=msg.covariance_type,
    )
    _set_time(proto.timestamp, msg.sensor_time_ns)
    return proto


def _fix_from_proto(proto, seq: int, log_time: int) -> GnssFix:
    return GnssFix(seq, _get_time(proto.timestamp), log_time, proto.latitude, proto.longitude, proto.altitude,
                   tuple(proto.position_covariance), proto.position_covariance_type)


def _pose_to_proto(msg: VehiclePose) -> PoseInFrame:
    proto = PoseInFrame(frame_id=msg.frame_id)
    _set_time(proto.timestamp, msg.sensor_time_ns)
    p, q = proto.pose.position, proto.pose.orientation
    p.x, p.y, p.z = msg.position_m
    q.x, q.y, q.z, q.w = msg.orientation_xyzw
    return proto


def _pose_from_proto(proto, seq: int, log_time: int) -> VehiclePose:
    p, q = proto.pose.position, proto.pose.orientation
    return VehiclePose(seq, _get_time(proto.timestamp), log_time, proto.frame_id, (p.x, p.y, p.z),
                       (q.x, q.y, q.z, q.w))


_FROM_WELL_KNOWN = {
    ("CameraFrame", "foxglove.CompressedImage"): (CompressedImage, _camera_from_proto),
    ("CameraFrame", "foxglove.CompressedVideo"): (CompressedVideo, _camera_from_proto),
    ("CameraFrame", "foxglove.RawImage"): (RawImage, _camera_from_proto),
    ("SemanticMask", "foxglove.CompressedImage"): (CompressedImage, _mask_from_proto),
    ("GnssFix", "foxglove.LocationFix"): (LocationFix, _fix_from_proto),
    ("VehiclePose", "foxglove.PoseInFrame"): (PoseInFrame, _pose_from_proto),
}


def _to_well_known(msg: object):
    """The Foxglove protobuf of a message, or None when it has no well-known schema."""
    if isinstance(msg, CameraFrame):
        return _camera_to_proto(msg)
    if isinstance(msg, SemanticMask):
        return _mask_to_proto(msg)
    if isinstance(msg, GnssFix):
        return _fix_to_proto(msg)
    if isinstance(msg, VehiclePose):
        return _pose_to_proto(msg)
    return None


def calibration_json(config: CarConfig) -> str:
    """Intrinsics, distortion and extrinsics of every sensor, as JSON."""
    s = config.sensors
    cal = {"cameras": {c.name: {"width": c.width, "height": c.height, "model": c.model,
                                "intrinsics": c.intrinsics.model_dump(), "distortion": list(c.distortion),
                                "extrinsics": c.extrinsics.model_dump(mode="json")} for c in s.cameras}}
    if s.lidar is not None:
        cal["lidar"] = {"model": s.lidar.model, "extrinsics": s.lidar.extrinsics.model_dump(mode="json")}
    if s.gnss is not None:
        cal["gnss"] = {"antenna_lever_arm_m": list(s.gnss.antenna_lever_arm_m),
                       "imu_extrinsics": s.gnss.imu_extrinsics.model_dump(mode="json")}
    return json.dumps(cal)


_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class LogWriter:
    """Writes messages of the car's topics into one self-contained MCAP file."""

    def __init__(self, path: str | Path, config: CarConfig, metadata: dict[str, str] | None = None,
                 compression: str | None = None, chunk_size: int = 4 * 1024 * 1024,
                 config_path: str | Path | None = None):
        self.path = Path(path)
        self.config = config
        self._topics = topic_table(config)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=_COMPRESSION[compression or config.recorder.compression])
        self._writer.start(profile="", library=SOFTWARE_VERSION)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.last_seq: dict[str, int] = {}  # per topic, the highest message seq written
        self.bytes_written_estimate = 0
        self._closed = False
        meta = {
            "software_version": SOFTWARE_VERSION,
            "config": config_to_yaml(config),
            "calibration": calibration_json(config),
            "host": socket.gethostname(),
            "start_time_utc_ns": str(time.time_ns()),
            "start_mono_ns": str(time.monotonic_ns()),
        }
        if config.sensors.lidar is not None and config_path is not None:
            try:  # the Lidar's own calibration file, so the segment decodes on its own
                meta["lidar_metadata"] = resolve_path(config_path, config.sensors.lidar.metadata_file).read_text()
            except OSError as exc:
                meta["lidar_metadata_error"] = str(exc)
        meta.update(metadata or {})
        self._writer.add_metadata(METADATA_NAME, meta)
        self._write_calibrations()

    def _schema_id(self, name: str, data: bytes) -> int:  # data is only built for a new channel
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(name=name, encoding="protobuf", data=data)
        return self._schemas[name]

    def _channel_id(self, topic: str, schema_name: str, schema_bytes: Callable[[], bytes], type_name: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schema_id(schema_name, schema_bytes())
            cid = self._writer.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid,
                                                metadata={"roadlog.type": type_name})
            self._channels[topic] = cid
        return cid

    def _write_calibrations(self) -> None:
        for cam in self.config.sensors.cameras:
            proto = CameraCalibration(frame_id=cam.name, width=cam.width, height=cam.height,
                                      distortion_model="plumb_bob", D=list(cam.distortion),
                                      K=list(cam.intrinsics.matrix().ravel()))
            p = list(cam.intrinsics.matrix().ravel())
            proto.P.extend([p[0], p[1], p[2], 0.0, p[3], p[4], p[5], 0.0, p[6], p[7], p[8], 0.0])
            proto.R.extend([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0])
            topic = calibration_topic(cam.name)
            cid = self._channel_id(topic, "foxglove.CameraCalibration",
                                   lambda: _file_descriptor_set(CameraCalibration.DESCRIPTOR.file), "CameraCalibration")
            self._writer.add_message(cid, log_time=0, data=proto.SerializeToString(), publish_time=0)

    def write(self, topic: str, message: object) -> None:
        """Append one message; its topic must be in the car's topic table with a matching type."""
        spec = self._topics.get(topic)
        if spec is None:
            raise KeyError(f"topic {topic!r} is not in the topic table")
        if type(message) is not spec.message_type:
            raise TypeError(f"topic {topic!r} carries {spec.message_type.__name__}, got {type(message).__name__}")
        proto = _to_well_known(message)
        type_name = type(message).__name__
        if proto is not None:
            data = proto.SerializeToString()
            cid = self._channel_id(
                topic, proto.DESCRIPTOR.full_name, lambda: _file_descriptor_set(proto.DESCRIPTOR.file), type_name)
        else:
            data = message_codec.encode(message)
            cid = self._channel_id(
                topic, message_codec.schema_name(type(message)),
                lambda: message_codec.schema_data(type(message)), type_name)
        self._writer.add_message(cid, log_time=int(message.host_mono_ns), data=data,
                                 publish_time=int(message.sensor_time_ns), sequence=int(message.seq) & 0xFFFFFFFF)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.last_seq[topic] = max(self.last_seq.get(topic, -1), int(message.seq))
        self.bytes_written_estimate += len(data) + 32

    def close(self, extra_metadata: dict[str, str] | None = None) -> None:
        """Finish the file (summary, index, footer); `extra_metadata` goes in a `roadlog.counts` record."""
        if self._closed:
            return
        self._closed = True
        final = {"messages_per_topic": json.dumps(self.counts), "last_seq_per_topic": json.dumps(self.last_seq)}
        final.update(extra_metadata or {})
        self._writer.add_metadata(COUNTS_METADATA_NAME, final)
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()

    def flush(self) -> None:
        self._file.flush()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- reading ---------------------------------------------------------------------------------


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


def decode_record(schema: Schema | None, channel: Channel, message: Message) -> object | None:
    """The message dataclass of one MCAP message, or None for channels that are not roadlog topics."""
    type_name = channel.metadata.get("roadlog.type", "")
    msg_type = MESSAGE_TYPE_BY_NAME.get(type_name)
    if msg_type is None or schema is None:
        return None
    adapter = _FROM_WELL_KNOWN.get((type_name, schema.name))
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


def recover_log(src: str | Path, dst: str | Path, config: CarConfig) -> FileReport:
    """Rewrite a truncated file's complete records into a valid, closed file (with the source's own metadata:
    its config, host and start time); return what was kept."""
    report = ReadReport()
    metadata = dict(read_metadata(src, until=METADATA_NAME).get(METADATA_NAME, {}), recovered_from=str(src))
    with LogWriter(dst, config, metadata=metadata) as writer:
        for rec in read_log([src], report=report):
            writer.write(rec.topic, rec.message)
    return report.files[0]
