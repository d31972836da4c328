"""The shipped `.proto` files (daemon/log_format/proto/): current with the descriptors the writer stores, one for
every schema in a log, and enough to decode a log's messages with another protobuf implementation (protobufjs
from npm into tests/.node/, skipped with the reason when it cannot be installed)."""

from __future__ import annotations

import base64
import json
import os
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from google.protobuf.descriptor import FieldDescriptor
from mcap.reader import make_reader

from daemon.log_format.foxglove_schemas import to_well_known
from daemon.log_format.proto_files import PROTO_DIR, schema_files
from daemon.log_format.writer import LogWriter
from daemon.spine import message_codec
from daemon.spine.messages import SemanticMask
from tests.daemon.test_log_format import CONFIG, _messages
from tests.node_packages import node_modules

DECODE_JS = Path(__file__).with_name("proto_decode.js")
_LONGS = {FieldDescriptor.TYPE_INT64, FieldDescriptor.TYPE_UINT64, FieldDescriptor.TYPE_FIXED64,
          FieldDescriptor.TYPE_SINT64, FieldDescriptor.TYPE_SFIXED64}


def test_the_shipped_proto_files_are_current():
    shipped = {str(p.relative_to(PROTO_DIR)): p.read_text() for p in PROTO_DIR.rglob("*.proto")}
    assert shipped == schema_files(), "run: python -m daemon.log_format.proto_files"


@pytest.fixture(scope="module")
def log_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("proto") / "all.mcap"
    mask = np.arange(12, dtype=np.uint8).reshape(3, 4) % 6
    with LogWriter(path, CONFIG) as writer:
        for topic, msg in _messages(1):
            if isinstance(msg, SemanticMask):
                msg.data = cv2.imencode(".png", mask)[1].tobytes()  # a real mask: its colour image is logged too
            writer.write(topic, msg)
    return path


def one_message_per_schema(path: Path) -> dict[str, bytes]:
    out = {}
    with open(path, "rb") as f:
        for schema, _, message in make_reader(f).iter_messages():
            out.setdefault(schema.name, message.data)
    return out


def test_every_schema_in_a_log_has_its_proto_file(log_file):
    names = one_message_per_schema(log_file)
    assert len(names) == 13  # 6 roadlog messages, 3 image kinds, fixes, poses, calibrations, transforms
    for name in names:
        package, message = name.split(".")
        text = (PROTO_DIR / package / f"{message}.proto").read_text()
        assert f"package {package};" in text and f"message {message} {{" in text


def as_object(proto) -> dict:
    """The fields a message sets, as protobufjs's toObject writes them (longs and bytes as strings, enum names)."""
    out = {}
    for field, value in proto.ListFields():
        def one(v, field=field):
            if field.type == FieldDescriptor.TYPE_MESSAGE:
                return as_object(v)
            if field.type in _LONGS:
                return str(v)
            if field.type == FieldDescriptor.TYPE_BYTES:
                return base64.b64encode(v).decode()
            if field.type == FieldDescriptor.TYPE_ENUM:
                return field.enum_type.values_by_number[v].name
            return v
        repeated = field.is_repeated if hasattr(field, "is_repeated") else field.label == FieldDescriptor.LABEL_REPEATED
        out[field.name] = [one(v) for v in value] if repeated else one(value)
    return out


def python_proto(schema_name: str, data: bytes):
    for _, msg in _messages(1):  # the Python class behind the schema
        well_known = to_well_known(msg)
        if well_known is not None and well_known.DESCRIPTOR.full_name == schema_name:
            proto = type(well_known)()
            break
        if message_codec.schema_name(type(msg)) == schema_name:
            proto = message_codec._proto_classes()[type(msg)]()
            break
    else:
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
        from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
        proto = {"foxglove.CameraCalibration": CameraCalibration, "foxglove.FrameTransforms": FrameTransforms}[
            schema_name]()
    proto.ParseFromString(data)
    return proto


@pytest.fixture(scope="module")
def protobufjs() -> Path:
    return node_modules("protobufjs@7")


def contains(js, py) -> bool:
    """Every field Python set has the same value in protobufjs's object (which also lists the defaults)."""
    if isinstance(py, dict):
        return isinstance(js, dict) and all(contains(js.get(k), v) for k, v in py.items())
    if isinstance(py, list):
        return isinstance(js, list) and len(js) == len(py) and all(map(contains, js, py))
    return js == py


def test_another_protobuf_implementation_decodes_a_log_from_the_shipped_files(log_file, protobufjs):
    payloads = one_message_per_schema(log_file)
    requests = [{"file": f"{name.split('.')[0]}/{name.split('.')[1]}.proto", "type": name,
                 "data": base64.b64encode(data).decode()} for name, data in payloads.items()]
    done = subprocess.run(["node", str(DECODE_JS), str(PROTO_DIR)], input=json.dumps(requests), capture_output=True,
                          text=True, timeout=120, env=dict(os.environ, NODE_PATH=str(protobufjs)))
    assert done.returncode == 0, done.stderr
    decoded = json.loads(done.stdout)
    for (name, data), js in zip(payloads.items(), decoded, strict=True):
        py = as_object(python_proto(name, data))
        assert py, name
        assert contains(js, py), (name, js, py)
