"""The `.proto` files of every schema a log holds, shipped in `daemon/log_format/proto/`: the `roadlog.<Name>` messages
(derived from the dataclasses by daemon.spine.message_codec) and the Foxglove schemas the writer uses, each rendered
from the very descriptor the writer stores in the file. `python -m daemon.log_format.proto_files` writes them again
(a test checks the shipped ones are current)."""

from __future__ import annotations

import sys
from pathlib import Path

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor

from daemon.spine import message_codec
from daemon.spine.messages import MESSAGE_TYPES

PROTO_DIR = Path(__file__).with_name("proto")
FOXGLOVE_MESSAGES = (CameraCalibration, CompressedImage, CompressedVideo, FrameTransforms, LocationFix, PointCloud,
                     PoseInFrame, RawImage)

_F = descriptor_pb2.FieldDescriptorProto
_SCALAR_NAMES = {_F.TYPE_DOUBLE: "double", _F.TYPE_FLOAT: "float", _F.TYPE_INT64: "int64", _F.TYPE_UINT64: "uint64",
                 _F.TYPE_INT32: "int32", _F.TYPE_FIXED64: "fixed64", _F.TYPE_FIXED32: "fixed32", _F.TYPE_BOOL: "bool",
                 _F.TYPE_STRING: "string", _F.TYPE_BYTES: "bytes", _F.TYPE_UINT32: "uint32",
                 _F.TYPE_SFIXED32: "sfixed32", _F.TYPE_SFIXED64: "sfixed64", _F.TYPE_SINT32: "sint32",
                 _F.TYPE_SINT64: "sint64"}


def _field_line(f: descriptor_pb2.FieldDescriptorProto) -> str:
    label = "repeated " if f.label == _F.LABEL_REPEATED else ("optional " if f.proto3_optional else "")
    kind = f.type_name if f.type in (_F.TYPE_MESSAGE, _F.TYPE_ENUM) else _SCALAR_NAMES[f.type]  # ".pkg.Name"
    return f"{label}{kind} {f.name} = {f.number};"


def _enum_lines(enum: descriptor_pb2.EnumDescriptorProto, indent: str) -> list[str]:
    return [f"{indent}enum {enum.name} {{", *(f"{indent}  {v.name} = {v.number};" for v in enum.value), f"{indent}}}"]


def _message_lines(msg: descriptor_pb2.DescriptorProto, indent: str) -> list[str]:
    if any(not f.proto3_optional for f in msg.field if f.HasField("oneof_index")) or msg.extension_range:
        raise ValueError(f"{msg.name}: oneofs and extensions are not rendered")
    lines = [f"{indent}message {msg.name} {{"]
    for enum in msg.enum_type:
        lines += _enum_lines(enum, indent + "  ")
    for nested in msg.nested_type:
        lines += _message_lines(nested, indent + "  ")
    lines += [indent + "  " + _field_line(f) for f in msg.field]
    return lines + [f"{indent}}}"]


def proto_text(fdp: descriptor_pb2.FileDescriptorProto) -> str:
    """A FileDescriptorProto as the `.proto` source it describes."""
    lines = ["// Generated from the descriptor roadlog's writer stores in each log (daemon/log_format/proto_files.py).",
             f'syntax = "{fdp.syntax or "proto2"}";', "", f"package {fdp.package};", ""]
    lines += [f'import "{dep}";' for dep in fdp.dependency] + ([""] if fdp.dependency else [])
    for enum in fdp.enum_type:
        lines += _enum_lines(enum, "") + [""]
    for msg in fdp.message_type:
        lines += _message_lines(msg, "") + [""]
    return "\n".join(lines)


def _with_dependencies(fd: FileDescriptor, out: dict[str, descriptor_pb2.FileDescriptorProto]) -> None:
    for dep in fd.dependencies:
        _with_dependencies(dep, out)
    if fd.name not in out and not fd.name.startswith("google/protobuf/"):  # every protobuf tool has those
        fdp = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(fdp)
        out[fd.name] = fdp


def schema_files() -> dict[str, str]:
    """Relative path -> `.proto` text of every schema a log may hold."""
    files: dict[str, descriptor_pb2.FileDescriptorProto] = {}
    for cls in FOXGLOVE_MESSAGES:
        _with_dependencies(cls.DESCRIPTOR.file, files)
    for message_type in MESSAGE_TYPES:
        fdp = message_codec.file_descriptor(message_type)
        files[fdp.name] = fdp
    return {name: proto_text(fdp) for name, fdp in sorted(files.items())}


def write_proto_files(folder: Path = PROTO_DIR) -> list[Path]:
    written = []
    for name, text in schema_files().items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        written.append(path)
    return written


if __name__ == "__main__":
    for written_path in write_proto_files(Path(sys.argv[1]) if len(sys.argv) > 1 else PROTO_DIR):
        print(written_path)
