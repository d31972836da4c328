"""Point clouds in the log: our PointCloud records round-trip through a real MCAP file as foxglove.PointCloud, another
tool's PointCloud layouts read back into ours, malformed ones are counted, never fatal."""

import json

import numpy as np
import pytest
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud as FoxglovePointCloud
from mcap.reader import make_reader
from mcap.writer import Writer

from daemon.log_format.foxglove_schemas import file_descriptor_set
from daemon.log_format.metadata_records import log_time_offset
from daemon.log_format.reader import ReadReport, read_log, read_metadata
from daemon.log_format.writer import LogWriter
from daemon.spine.messages import PointCloud
from daemon.spine.point_cloud_codec import POINT_FIELDS, POINT_STRIDE, pack_points, point_array
from daemon.spine.topics import LIDAR_POINTS
from tests.daemon_fixtures import private_config

F = PackedElementField


def _scan(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = rng.normal(0.0, 20.0, (n, 3)).astype(np.float32)
    return xyz, rng.uniform(0, 255, n).astype(np.float32), np.sort(rng.uniform(0, 0.1, n)).astype(np.float32)


def test_pack_points_and_point_array_are_inverse_and_check_their_shapes():
    xyz, intensity, time_s = _scan(np.random.default_rng(0), 1000)
    cloud = PointCloud(data=pack_points(xyz, intensity, time_s))
    assert len(cloud.data) == 1000 * POINT_STRIDE == 1000 * 20 and POINT_FIELDS == ("x", "y", "z", "intensity", "time")
    points = point_array(cloud)
    assert points.shape == (1000, 5) and points.dtype == np.float32
    assert np.array_equal(points[:, :3], xyz) and np.array_equal(points[:, 3], intensity)
    assert np.array_equal(points[:, 4], time_s)
    assert np.array_equal(point_array(PointCloud(data=pack_points(xyz)))[:, 3:], np.zeros((1000, 2)))  # none given
    assert np.frombuffer(cloud.data[:20], "<f4").tolist() == points[0].tolist()  # little-endian records
    with pytest.raises(ValueError, match="whole number"):
        point_array(PointCloud(data=cloud.data[:-3]))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        pack_points(xyz[:, :2])
    with pytest.raises(ValueError, match="intensity has 999 values"):
        pack_points(xyz, intensity[:-1])


def test_point_clouds_round_trip_through_an_mcap_file_as_foxglove_point_clouds(tmp_path):
    config, config_path = private_config(tmp_path, point_clouds=True)
    rng = np.random.default_rng(1)
    sent, scans = [], []
    for i in range(5):
        scans.append(_scan(rng, 2000 + 500 * i))
        sent.append(PointCloud(i, 1_700_000_000_000_000_000 + i * 100_000_000, 5_000_000_000 + i * 100_000_000,
                               "lidar", pack_points(*scans[-1])))
    path = tmp_path / "points.mcap"
    with LogWriter(path, config, config_path=config_path) as writer:
        for cloud in sent:
            writer.write(LIDAR_POINTS, cloud)
    back = [r.message for r in read_log([path], topics=[LIDAR_POINTS])]
    assert back == sent
    recorded = read_metadata(path)["roadlog"]  # the Lidar's model and mounting, no Ouster metadata to record
    assert json.loads(recorded["calibration"])["lidar"] == {
        "model": "point-cloud", "extrinsics": config.sensors.lidar.extrinsics.model_dump(mode="json")}
    assert "lidar_metadata" not in recorded and "lidar_metadata_error" not in recorded
    for cloud, (xyz, intensity, time_s) in zip(back, scans, strict=True):
        points = point_array(cloud)
        assert np.array_equal(points[:, :3], xyz) and np.array_equal(points[:, 3], intensity)
        assert np.array_equal(points[:, 4], time_s)
    with open(path, "rb") as f:  # what Foxglove sees: the well-known schema, our fields at their offsets
        reader = make_reader(f)
        schema, channel, message = next(reader.iter_messages(topics=[LIDAR_POINTS]))
    assert schema.name == "foxglove.PointCloud" and channel.metadata["roadlog.type"] == "PointCloud"
    proto = FoxglovePointCloud()
    proto.ParseFromString(message.data)
    assert proto.frame_id == "lidar" and proto.point_stride == 20
    assert [(f.name, f.offset, f.type) for f in proto.fields] == [
        ("x", 0, F.FLOAT32), ("y", 4, F.FLOAT32), ("z", 8, F.FLOAT32), ("intensity", 12, F.FLOAT32),
        ("time", 16, F.FLOAT32)]
    assert proto.timestamp.seconds * 10**9 + proto.timestamp.nanos == sent[0].sensor_time_ns
    # the log time is UTC: the host time moved by the file's one offset, which the channel names
    assert message.log_time == sent[0].host_mono_ns + log_time_offset(channel.metadata) > 1.6e18
    assert message.publish_time == sent[0].sensor_time_ns


def _foreign_log(path, clouds: list[FoxglovePointCloud | bytes]) -> None:
    """A log as another tool writes it: foxglove.PointCloud on lidar/points, no roadlog metadata at all."""
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema("foxglove.PointCloud", "protobuf",
                                        file_descriptor_set(FoxglovePointCloud.DESCRIPTOR.file))
        channel = writer.register_channel(LIDAR_POINTS, "protobuf", schema)
        for i, cloud in enumerate(clouds):
            data = cloud if isinstance(cloud, bytes) else cloud.SerializeToString()
            writer.add_message(channel, log_time=1000 + i, data=data, publish_time=1000 + i, sequence=i)
        writer.finish()


def _foreign_cloud(fields: list[tuple[str, int, int]], stride: int, values: dict[str, np.ndarray],
                   frame_id: str = "os_sensor") -> FoxglovePointCloud:
    """A cloud in the given layout (name, offset, numeric type) holding `values` per field name."""
    types = {F.FLOAT32: "<f4", F.FLOAT64: "<f8", F.UINT16: "<u2", F.UINT8: "u1", F.INT32: "<i4"}
    n = len(next(iter(values.values())))
    buffer = np.zeros((n, stride), np.uint8)
    for name, offset, kind in fields:
        size = np.dtype(types[kind]).itemsize
        buffer[:, offset:offset + size] = np.asarray(values[name], types[kind]).reshape(n, 1).view(np.uint8)
    proto = FoxglovePointCloud(frame_id=frame_id, point_stride=stride, data=buffer.tobytes())
    proto.timestamp.seconds, proto.timestamp.nanos = 1_700_000_000, 250_000_000
    for name, offset, kind in fields:
        proto.fields.add(name=name, offset=offset, type=kind)
    return proto


def test_another_tools_point_cloud_layouts_read_back_into_ours(tmp_path):
    rng = np.random.default_rng(2)
    n = 300
    x, y, z = (rng.normal(0, 10, n) for _ in range(3))
    intensity, t, ring = rng.uniform(0, 1000, n), np.sort(rng.uniform(0, 0.1, n)), rng.integers(0, 128, n)
    # FLOAT64, another order, extra fields (ring, an rgb word), a padded stride
    doubles = _foreign_cloud([("time", 0, F.FLOAT64), ("ring", 8, F.UINT16), ("z", 10, F.FLOAT64),
                              ("intensity", 18, F.FLOAT32), ("x", 22, F.FLOAT64), ("rgb", 30, F.INT32),
                              ("y", 34, F.FLOAT64)], 48,
                             {"time": t, "ring": ring, "z": z, "intensity": intensity, "x": x, "rgb": ring, "y": y})
    bare = _foreign_cloud([("x", 0, F.FLOAT32), ("y", 4, F.FLOAT32), ("z", 8, F.FLOAT32)], 16, {"x": x, "y": y, "z": z})
    integers = _foreign_cloud([("x", 0, F.FLOAT32), ("y", 4, F.FLOAT32), ("z", 8, F.FLOAT32),
                               ("intensity", 12, F.UINT8)], 13, {"x": x, "y": y, "z": z, "intensity": ring})
    moved = _foreign_cloud([("x", 0, F.FLOAT32), ("y", 4, F.FLOAT32), ("z", 8, F.FLOAT32)], 12,
                           {"x": x, "y": y, "z": z})
    moved.pose.position.x, moved.pose.position.z = 1.0, 2.0  # the cloud's origin in its frame, turned 90 degrees left
    moved.pose.orientation.z, moved.pose.orientation.w = np.sqrt(0.5), np.sqrt(0.5)
    path = tmp_path / "foreign.mcap"
    _foreign_log(path, [doubles, bare, integers, moved])
    report = ReadReport()
    back = [r.message for r in read_log([path], report=report)]
    assert report.files[0].undecodable == 0 and len(back) == 4
    assert all(m.sensor == "os_sensor" and m.sensor_time_ns == 1_700_000_000_250_000_000 for m in back)
    assert [m.seq for m in back] == [0, 1, 2, 3] and [m.host_mono_ns for m in back] == [1000, 1001, 1002, 1003]
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731 - our records hold float32
    points = point_array(back[0])
    assert np.array_equal(points, np.column_stack([f32(x), f32(y), f32(z), f32(intensity), f32(t)]))
    assert np.array_equal(point_array(back[1]), np.column_stack([f32(x), f32(y), f32(z), np.zeros((n, 2))]))
    assert np.array_equal(point_array(back[2])[:, 3], ring.astype(np.uint8).astype(np.float32))
    expected = np.column_stack([1.0 - f32(y).astype(np.float64), f32(x), f32(z) + 2.0])
    np.testing.assert_allclose(point_array(back[3])[:, :3], expected, atol=1e-5)


def test_malformed_point_clouds_are_counted_undecodable_and_the_rest_is_read(tmp_path):
    x = np.arange(10.0)
    good = _foreign_cloud([("x", 0, F.FLOAT32), ("y", 4, F.FLOAT32), ("z", 8, F.FLOAT32)], 12, {"x": x, "y": x, "z": x})
    no_z = _foreign_cloud([("x", 0, F.FLOAT32), ("y", 4, F.FLOAT32)], 8, {"x": x, "y": x})
    torn = FoxglovePointCloud()
    torn.CopyFrom(good)
    torn.data = good.data[:-5]  # not a whole number of points
    past_stride = FoxglovePointCloud()
    past_stride.CopyFrom(good)
    past_stride.point_stride = 10  # z runs past the point's end
    zero_stride = FoxglovePointCloud()
    zero_stride.CopyFrom(good)
    zero_stride.point_stride = 0
    unknown_type = FoxglovePointCloud()
    unknown_type.CopyFrom(good)
    unknown_type.fields[2].type = F.UNKNOWN
    ours_torn = FoxglovePointCloud(frame_id="lidar", point_stride=20, data=bytes(30))  # our layout, 1.5 points
    for k, name in enumerate(POINT_FIELDS):
        ours_torn.fields.add(name=name, offset=4 * k, type=F.FLOAT32)
    path = tmp_path / "malformed.mcap"
    _foreign_log(path, [no_z, good, torn, past_stride, zero_stride, unknown_type, ours_torn, b"\xff\x01not protobuf",
                        good])
    report = ReadReport()
    back = [r.message for r in read_log([path], report=report)]
    assert report.files[0].undecodable == 7 and report.files[0].messages == 2
    assert [m.seq for m in back] == [1, 8] and np.array_equal(point_array(back[0])[:, 0], x)
