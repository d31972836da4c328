"""Binary encoding of messages: protobuf schemas derived from the message dataclasses.

The dataclasses in `daemon.spine.messages` are the one definition; this module derives a protobuf message
type `roadlog.<Name>` from each (int -> int64/uint64, float -> double, str -> string, bytes -> bytes,
bool -> bool, tuples of floats -> repeated double). The same encoding is used on the bus and, for
messages without a Foxglove well-known schema, in the logs.
"""

from __future__ import annotations

import dataclasses
import functools
import typing

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from daemon.spine import messages as messages_module
from daemon.spine.messages import MESSAGE_TYPES, bulk_field

_F = descriptor_pb2.FieldDescriptorProto
_SCALARS = {int: _F.TYPE_INT64, float: _F.TYPE_DOUBLE, str: _F.TYPE_STRING, bytes: _F.TYPE_BYTES, bool: _F.TYPE_BOOL}
PACKAGE = "roadlog"


def schema_name(message_type: type) -> str:
    return f"{PACKAGE}.{message_type.__name__}"


def _field_proto(name: str, number: int, annotation: object) -> descriptor_pb2.FieldDescriptorProto:
    if typing.get_origin(annotation) is tuple:
        return _F(name=name, number=number, type=_F.TYPE_DOUBLE, label=_F.LABEL_REPEATED)
    kind = _SCALARS[annotation]  # type: ignore[index]
    if name == "seq":
        kind = _F.TYPE_UINT64
    return _F(name=name, number=number, type=kind, label=_F.LABEL_OPTIONAL)


def file_descriptor(message_type: type) -> descriptor_pb2.FileDescriptorProto:
    """The .proto file (as a descriptor) of one message type."""
    hints = typing.get_type_hints(message_type, vars(messages_module))
    fdp = descriptor_pb2.FileDescriptorProto(
        name=f"{PACKAGE}/{message_type.__name__}.proto", package=PACKAGE, syntax="proto3"
    )
    msg = fdp.message_type.add(name=message_type.__name__)
    for number, f in enumerate(dataclasses.fields(message_type), start=1):
        msg.field.append(_field_proto(f.name, number, hints[f.name]))
    return fdp


@functools.cache
def schema_data(message_type: type) -> bytes:
    """A serialized FileDescriptorSet: the MCAP schema record's data for encoding "protobuf"."""
    fds = descriptor_pb2.FileDescriptorSet()
    fds.file.append(file_descriptor(message_type))
    return fds.SerializeToString()


@functools.cache
def _proto_classes() -> dict[type, type]:
    pool = descriptor_pool.DescriptorPool()
    classes = {}
    for t in MESSAGE_TYPES:
        pool.Add(file_descriptor(t))
        classes[t] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name(t)))
    return classes


@functools.cache
def _fields(message_type: type) -> tuple[tuple[str, bool], ...]:
    hints = typing.get_type_hints(message_type, vars(messages_module))
    return tuple((f.name, typing.get_origin(hints[f.name]) is tuple) for f in dataclasses.fields(message_type))


def encode(message: object, *, without_bulk: bool = False) -> bytes:
    """Serialize a message dataclass (optionally leaving its bulk `data` field empty)."""
    proto = _proto_classes()[type(message)]()
    for name, repeated in _fields(type(message)):
        value = getattr(message, name)
        if name == "data":
            if without_bulk:
                continue
            value = bytes(value)
        if repeated:
            getattr(proto, name).extend(value)
        else:
            setattr(proto, name, value)
    return proto.SerializeToString()


def decode(message_type: type, data: bytes | memoryview, bulk: object = None) -> object:
    """Parse bytes made by `encode`; `bulk`, when given, becomes the `data` field without a copy."""
    proto = _proto_classes()[message_type]()
    proto.ParseFromString(bytes(data))
    values = {}
    for name, repeated in _fields(message_type):
        value = getattr(proto, name)
        values[name] = tuple(value) if repeated else value
    if bulk is not None:
        values["data"] = bulk
    return message_type(**values)


def encode_split(message: object) -> tuple[bytes, object]:
    """(meta, bulk) for the bus: meta is the message without its bulk field; bulk is `data` or b""."""
    bulk = getattr(message, "data", b"")
    return encode(message, without_bulk=True), bulk


def decode_split(message_type: type, meta: bytes | memoryview, bulk: object) -> object:
    return decode(message_type, meta, bulk if bulk_field(message_type) else None)
