"""Messages to and from Foxglove's well-known protobuf schemas: camera frames as CompressedImage /
CompressedVideo / RawImage, masks as CompressedImage, GNSS fixes as LocationFix, poses as PoseInFrame."""

from __future__ import annotations

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor

from daemon.spine.messages import RAW_FORMAT_CHANNELS, CameraFrame, GnssFix, SemanticMask, VehiclePose

_VIDEO_FORMATS = {"h264", "h265"}


def file_descriptor_set(file_descriptor: FileDescriptor) -> bytes:
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


def _frame_schema(msg: CameraFrame) -> type:
    if msg.format in RAW_FORMAT_CHANNELS:
        return RawImage
    return CompressedVideo if msg.format in _VIDEO_FORMATS else CompressedImage


def _camera_to_proto(msg: CameraFrame):
    cls = _frame_schema(msg)
    proto = cls(frame_id=msg.camera, data=bytes(msg.data))
    _set_time(proto.timestamp, msg.sensor_time_ns)
    if cls is RawImage:
        proto.width, proto.height, proto.encoding = msg.width, msg.height, msg.format
        proto.step = msg.width * RAW_FORMAT_CHANNELS[msg.format]
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


FROM_WELL_KNOWN = {  # (roadlog type, schema name) -> (protobuf class, from_proto)
    ("CameraFrame", "foxglove.CompressedImage"): (CompressedImage, _camera_from_proto),
    ("CameraFrame", "foxglove.CompressedVideo"): (CompressedVideo, _camera_from_proto),
    ("CameraFrame", "foxglove.RawImage"): (RawImage, _camera_from_proto),
    ("SemanticMask", "foxglove.CompressedImage"): (CompressedImage, _mask_from_proto),
    ("GnssFix", "foxglove.LocationFix"): (LocationFix, _fix_from_proto),
    ("VehiclePose", "foxglove.PoseInFrame"): (PoseInFrame, _pose_from_proto),
}


def to_well_known(msg: object):
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
