"""Writing: `LogWriter` maps camera frames, masks, GNSS fixes, poses and point clouds to Foxglove's well-known schemas
and every other message to its `roadlog.<Name>` schema derived from `daemon.spine.messages`. Each MCAP message record
carries sequence = the message's per-topic seq, log_time = UTC ns (host_mono_ns + the file's one log_time_offset_ns,
named in the `roadlog` record and in every channel's metadata) and publish_time = sensor_time_ns, so every field
round-trips. Each chunk holds its messages in log-time order (a message older than the chunk's last starts a new
chunk). Each file starts with a `roadlog` metadata record and holds a CameraCalibration channel per camera and the
car's static transforms (`tf_static`), both written with the first message at its log time, and each mask again in
colour (`mask_colour/<camera>`, mask_palette), and each live vehicle pose again as a transform (`tf`, the map frame to
the vehicle); each channel is also described by a `roadlog.channel` metadata record
outside the chunks (metadata_records)."""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Callable
from pathlib import Path

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer

from daemon.log_format.foxglove_schemas import file_descriptor_set, to_well_known
from daemon.log_format.mask_palette import coloured_mask_png
from daemon.log_format.metadata_records import (
    CHANNEL_METADATA_NAME,
    CHANNEL_OFFSET_KEY,
    COUNTS_METADATA_NAME,
    LOG_TIME_CLOCK_KEY,
    LOG_TIME_OFFSET_KEY,
    LOG_TIME_UTC,
    METADATA_NAME,
    SOFTWARE_VERSION,
    channel_record,
)
from daemon.log_format.static_transforms import static_transforms
from daemon.spine import message_codec
from daemon.spine.config import CarConfig, config_to_yaml, resolve_path
from daemon.spine.messages import SemanticMask, VehiclePose
from daemon.spine.topics import (
    LOG_ONLY_CHANNELS,
    TF,
    TF_STATIC,
    VEHICLE_FRAME,
    VEHICLE_POSE,
    calibration_topic,
    mask_colour_topic,
    topic_table,
)


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


def _log_time_offset(given: int | None, metadata: dict[str, str], measured: int) -> int:
    """UTC minus host monotonic time for the file: as given; as the caller's metadata names it (a recovered file
    keeps its source's); from the start times it pairs (a simulated drive's); else as measured now."""
    if given is not None:
        return int(given)
    if metadata.get(LOG_TIME_CLOCK_KEY) == LOG_TIME_UTC and LOG_TIME_OFFSET_KEY in metadata:
        return int(metadata[LOG_TIME_OFFSET_KEY])
    if "start_time_utc_ns" in metadata and "start_mono_ns" in metadata:
        return int(metadata["start_time_utc_ns"]) - int(metadata["start_mono_ns"])
    return measured


_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class LogWriter:
    """Writes messages of the car's topics into one self-contained MCAP file. `log_time_offset_ns`: what is added to
    each message's host_mono_ns to give its UTC log time (None: UTC now minus monotonic now; an importer whose host
    times already are UTC gives 0)."""

    def __init__(self, path: str | Path, config: CarConfig, metadata: dict[str, str] | None = None,
                 compression: str | None = None, chunk_size: int = 4 * 1024 * 1024,
                 config_path: str | Path | None = None, log_time_offset_ns: int | None = None):
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
        self._channel_records_pending: list[dict[str, str]] = []  # channels whose first chunk is not written yet
        self._file_position = 0
        self._chunk_end: int | None = None  # the last log time in the chunk being built
        self.chunks_started_out_of_order = 0  # chunks begun early so that each stays in log-time order
        self.masks_without_colour = 0
        self._calibrations_written = False
        meta = {
            "software_version": SOFTWARE_VERSION,
            "config": config_to_yaml(config),
            "calibration": calibration_json(config),
            "host": socket.gethostname(),
            "start_time_utc_ns": str(time.time_ns()),
            "start_mono_ns": str(time.monotonic_ns()),
        }
        if config.sensors.lidar is not None and config.sensors.lidar.metadata_file and config_path is not None:
            try:  # the Lidar's own calibration file, so the segment decodes on its own
                meta["lidar_metadata"] = resolve_path(config_path, config.sensors.lidar.metadata_file).read_text()
            except OSError as exc:
                meta["lidar_metadata_error"] = str(exc)
        measured = int(meta["start_time_utc_ns"]) - int(meta["start_mono_ns"])
        meta.update(metadata or {})
        self.log_time_offset_ns = _log_time_offset(log_time_offset_ns, metadata or {}, measured)
        meta[LOG_TIME_CLOCK_KEY], meta[LOG_TIME_OFFSET_KEY] = LOG_TIME_UTC, str(self.log_time_offset_ns)
        self._start_log_time = int(meta["start_mono_ns"]) + self.log_time_offset_ns
        self._writer.add_metadata(METADATA_NAME, meta)
        self._file_position = self._file.tell()

    def _schema_id(self, name: str, data: bytes) -> int:  # data is only built for a new channel
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(name=name, encoding="protobuf", data=data)
        return self._schemas[name]

    def _channel_id(self, topic: str, schema_name: str, schema_bytes: Callable[[], bytes], type_name: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schema_id(schema_name, schema_bytes())
            metadata = {"roadlog.type": type_name, CHANNEL_OFFSET_KEY: str(self.log_time_offset_ns)}
            cid = self._writer.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid,
                                                metadata=metadata)
            self._channels[topic] = cid
            # outside the chunks too, now and again once the chunk holding the channel's own record is written: that
            # chunk may be the one a power cut tears, and the chunks after it still need the channel
            record = channel_record(
                Channel(id=cid, topic=topic, message_encoding="protobuf", schema_id=sid, metadata=metadata),
                Schema(id=sid, name=schema_name, encoding="protobuf", data=b""))
            self._writer.add_metadata(CHANNEL_METADATA_NAME, record)
            self._channel_records_pending.append(record)
            self._file_position = self._file.tell()
        return cid

    def _add_message(self, cid: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        if self._chunk_end is not None and log_time < self._chunk_end:
            self._writer.flush()  # finish the chunk: each chunk's messages stay in log-time order
            self.chunks_started_out_of_order += 1
            self._chunk_written()
        self._writer.add_message(cid, log_time=log_time, data=data, publish_time=publish_time, sequence=sequence)
        if self._file.tell() != self._file_position:  # the chunk holding this message was written
            self._chunk_written()
        else:
            self._chunk_end = log_time

    def _chunk_written(self) -> None:
        self._chunk_end = None
        for record in self._channel_records_pending:
            self._writer.add_metadata(CHANNEL_METADATA_NAME, record)
        self._channel_records_pending.clear()
        self._file_position = self._file.tell()

    def _write_calibrations(self, log_time: int) -> None:
        """A CameraCalibration per camera and the static transforms at `log_time` (the first message's, so a viewer
        has them from the start)."""
        self._calibrations_written = True
        cid = self._channel_id(TF_STATIC, "foxglove.FrameTransforms",
                               lambda: file_descriptor_set(FrameTransforms.DESCRIPTOR.file), "FrameTransforms")
        self._add_message(cid, log_time=log_time, data=static_transforms(self.config).SerializeToString(),
                          publish_time=log_time)
        for cam in self.config.sensors.cameras:
            proto = CameraCalibration(frame_id=cam.name, width=cam.width, height=cam.height,
                                      distortion_model="plumb_bob", D=list(cam.distortion),
                                      K=list(cam.intrinsics.matrix().ravel()))
            p = list(cam.intrinsics.matrix().ravel())
            proto.P.extend([p[0], p[1], p[2], 0.0, p[3], p[4], p[5], 0.0, p[6], p[7], p[8], 0.0])
            proto.R.extend([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0])
            topic = calibration_topic(cam.name)
            cid = self._channel_id(topic, "foxglove.CameraCalibration",
                                   lambda: file_descriptor_set(CameraCalibration.DESCRIPTOR.file), "CameraCalibration")
            self._add_message(cid, log_time=log_time, data=proto.SerializeToString(), publish_time=log_time)

    def write(self, topic: str, message: object) -> None:
        """Append one message; its topic must be in the car's topic table (or be a log-only channel) with a
        matching type."""
        spec = self._topics.get(topic)
        message_type = spec.message_type if spec is not None else LOG_ONLY_CHANNELS.get(topic)
        if message_type is None:
            raise KeyError(f"topic {topic!r} is not in the topic table")
        if type(message) is not message_type:
            raise TypeError(f"topic {topic!r} carries {message_type.__name__}, got {type(message).__name__}")
        log_time = int(message.host_mono_ns) + self.log_time_offset_ns
        if not self._calibrations_written:
            self._write_calibrations(log_time)
        proto = to_well_known(message)
        type_name = type(message).__name__
        if proto is not None:
            data = proto.SerializeToString()
            cid = self._channel_id(
                topic, proto.DESCRIPTOR.full_name, lambda: file_descriptor_set(proto.DESCRIPTOR.file), type_name)
        else:
            data = message_codec.encode(message)
            cid = self._channel_id(
                topic, message_codec.schema_name(type(message)),
                lambda: message_codec.schema_data(type(message)), type_name)
        self._add_message(cid, log_time=log_time, data=data, publish_time=int(message.sensor_time_ns),
                          sequence=int(message.seq) & 0xFFFFFFFF)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.last_seq[topic] = max(self.last_seq.get(topic, -1), int(message.seq))
        self.bytes_written_estimate += len(data) + 32
        if isinstance(message, SemanticMask):
            self._write_mask_colour(message, log_time)
        elif topic == VEHICLE_POSE:
            self._write_frame_transform(message, log_time)

    def _write_frame_transform(self, pose: VehiclePose, log_time: int) -> None:
        """The live pose again as the transform of its frame (the local map frame) to the vehicle frame on `tf`, so
        the 3D panel moves the car, and with it every sensor frame of `tf_static`."""
        proto = FrameTransform(parent_frame_id=pose.frame_id, child_frame_id=VEHICLE_FRAME)
        proto.timestamp.seconds, proto.timestamp.nanos = divmod(int(pose.sensor_time_ns), 1_000_000_000)
        proto.translation.x, proto.translation.y, proto.translation.z = pose.position_m
        q = proto.rotation
        q.x, q.y, q.z, q.w = pose.orientation_xyzw
        cid = self._channel_id(TF, "foxglove.FrameTransform",
                               lambda: file_descriptor_set(FrameTransform.DESCRIPTOR.file), "VehicleFrameTransform")
        data = proto.SerializeToString()
        self._add_message(cid, log_time=log_time, data=data, publish_time=int(pose.sensor_time_ns),
                          sequence=int(pose.seq) & 0xFFFFFFFF)
        self.bytes_written_estimate += len(data) + 32

    def _write_mask_colour(self, mask: SemanticMask, log_time: int) -> None:
        """The mask again as a paletted PNG (its class colours) on `mask_colour/<camera>`; a mask that is not an 8-bit
        greyscale PNG has none (counted in `masks_without_colour`)."""
        png = coloured_mask_png(bytes(mask.data)) if mask.format == "png" else None
        if png is None:
            self.masks_without_colour += 1
            return
        proto = CompressedImage(frame_id=mask.camera, format="png", data=png)
        proto.timestamp.seconds, proto.timestamp.nanos = divmod(int(mask.sensor_time_ns), 1_000_000_000)
        cid = self._channel_id(mask_colour_topic(mask.camera), "foxglove.CompressedImage",
                               lambda: file_descriptor_set(CompressedImage.DESCRIPTOR.file), "SemanticMaskColour")
        data = proto.SerializeToString()
        self._add_message(cid, log_time=log_time, data=data, publish_time=int(mask.sensor_time_ns),
                          sequence=int(mask.seq) & 0xFFFFFFFF)
        self.bytes_written_estimate += len(data) + 32

    def close(self, extra_metadata: dict[str, str] | None = None) -> None:
        """Finish the file (summary, index, footer); `extra_metadata` goes in a `roadlog.counts` record."""
        if self._closed:
            return
        self._closed = True
        if not self._calibrations_written:
            self._write_calibrations(self._start_log_time)
        final = {"messages_per_topic": json.dumps(self.counts), "last_seq_per_topic": json.dumps(self.last_seq),
                 "chunks_started_out_of_order": str(self.chunks_started_out_of_order),
                 "masks_without_colour": str(self.masks_without_colour)}
        final.update(extra_metadata or {})
        self._writer.add_metadata(COUNTS_METADATA_NAME, final)
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()

    def flush(self) -> None:
        """Finish the chunk in progress and hand everything to the OS (the caller fsyncs): what was added so far
        is then in the file, not only in the chunk being built (up to `chunk_size`: minutes of a slow topic)."""
        if self._chunk_end is not None:  # a chunk with messages is being built
            self._writer.flush()
            self._chunk_written()
        self._file.flush()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
