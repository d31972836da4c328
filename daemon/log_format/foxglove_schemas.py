"""Messages to and from Foxglove's well-known protobuf schemas: camera frames as CompressedImage /
CompressedVideo / RawImage, masks as CompressedImage, GNSS fixes as LocationFix, poses as PoseInFrame, point clouds
as PointCloud (any other tool's PointCloud layout read back into ours)."""

from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud as FoxglovePointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor

from daemon.spine.messages import RAW_FORMAT_CHANNELS, CameraFrame, GnssFix, PointCloud, SemanticMask, VehiclePose
from daemon.spine.point_cloud_codec import POINT_FIELDS, POINT_STRIDE, pack_points

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


_F = PackedElementField
_NUMPY_TYPES = {_F.UINT8: "u1", _F.INT8: "i1", _F.UINT16: "<u2", _F.INT16: "<i2", _F.UINT32: "<u4", _F.INT32: "<i4",
                _F.FLOAT32: "<f4", _F.FLOAT64: "<f8"}
_OUR_LAYOUT = [(name, 4 * k, _F.FLOAT32) for k, name in enumerate(POINT_FIELDS)]


def _cloud_to_proto(msg: PointCloud) -> FoxglovePointCloud:
    proto = FoxglovePointCloud(frame_id=msg.sensor, point_stride=POINT_STRIDE, data=bytes(msg.data))
    _set_time(proto.timestamp, msg.sensor_time_ns)
    proto.pose.orientation.w = 1.0
    for name, offset, kind in _OUR_LAYOUT:
        proto.fields.add(name=name, offset=offset, type=kind)
    return proto


def _pose_matrix(proto: FoxglovePointCloud) -> np.ndarray | None:
    """The 3x4 [R | t] of the cloud's pose in its frame, None for the identity (or no pose)."""
    p, q = proto.pose.position, proto.pose.orientation
    if (p.x, p.y, p.z) == (0, 0, 0) and (q.x, q.y, q.z) == (0, 0, 0):
        return None
    x, y, z, w = np.array([q.x, q.y, q.z, q.w]) / np.linalg.norm([q.x, q.y, q.z, q.w])
    rotation = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    return np.column_stack([rotation, [p.x, p.y, p.z]])


def _points_in_our_layout(proto: FoxglovePointCloud) -> bytes:
    """The cloud's points as our records (daemon.spine.point_cloud_codec): as they are when they are, else repacked
    from the fields x, y, z and, if present, intensity and time (seconds after the timestamp; 0 when absent), of any
    numeric type, moved by the cloud's pose. A cloud without x, y or z, or whose data do not fit its fields and
    stride, raises ValueError (the reader counts it undecodable)."""
    data, stride = proto.data, proto.point_stride
    if [(f.name, f.offset, f.type) for f in proto.fields] == _OUR_LAYOUT and stride == POINT_STRIDE:
        pose = _pose_matrix(proto)
        if pose is None:
            if len(data) % POINT_STRIDE:
                raise ValueError(f"{len(data)} bytes of points is not a whole number of {POINT_STRIDE}-byte points")
            return data
    fields = {f.name: f for f in proto.fields if f.name in POINT_FIELDS}
    if not {"x", "y", "z"} <= set(fields):
        raise ValueError(f"point cloud without x, y and z fields (has {[f.name for f in proto.fields]})")
    if any(f.type not in _NUMPY_TYPES for f in fields.values()):
        raise ValueError(f"point cloud field of unknown type: {[(f.name, f.type) for f in fields.values()]}")
    if stride <= 0 or len(data) % stride or any(
            f.offset + np.dtype(_NUMPY_TYPES[f.type]).itemsize > stride for f in fields.values()):
        raise ValueError(f"point cloud of {len(data)} bytes does not fit its point_stride {stride} and fields")
    dtype = np.dtype({"names": list(fields), "formats": [_NUMPY_TYPES[f.type] for f in fields.values()],
                      "offsets": [f.offset for f in fields.values()], "itemsize": stride})
    records = np.frombuffer(data, dtype)
    xyz = np.column_stack([records["x"], records["y"], records["z"]]).astype(np.float64)
    pose = _pose_matrix(proto)
    if pose is not None:
        xyz = xyz @ pose[:, :3].T + pose[:, 3]
    return pack_points(xyz, records["intensity"] if "intensity" in fields else None,
                       records["time"] if "time" in fields else None)


def _cloud_from_proto(proto: FoxglovePointCloud, seq: int, log_time: int) -> PointCloud:
    return PointCloud(seq, _get_time(proto.timestamp), log_time, proto.frame_id, _points_in_our_layout(proto))


# The roadlog type of a channel that another tool wrote (no `roadlog.type` channel metadata), where its schema can
# only be one roadlog message
TYPE_OF_FOREIGN_SCHEMA = {"foxglove.PointCloud": "PointCloud"}

FROM_WELL_KNOWN = {  # (roadlog type, schema name) -> (protobuf class, from_proto)
    ("CameraFrame", "foxglove.CompressedImage"): (CompressedImage, _camera_from_proto),
    ("CameraFrame", "foxglove.CompressedVideo"): (CompressedVideo, _camera_from_proto),
    ("CameraFrame", "foxglove.RawImage"): (RawImage, _camera_from_proto),
    ("SemanticMask", "foxglove.CompressedImage"): (CompressedImage, _mask_from_proto),
    ("GnssFix", "foxglove.LocationFix"): (LocationFix, _fix_from_proto),
    ("VehiclePose", "foxglove.PoseInFrame"): (PoseInFrame, _pose_from_proto),
    ("PointCloud", "foxglove.PointCloud"): (FoxglovePointCloud, _cloud_from_proto),
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
    if isinstance(msg, PointCloud):
        return _cloud_to_proto(msg)
    return None
