"""What Foxglove needs beside the messages, in a segment the real recorder wrote: the static transforms (vehicle ->
each sensor from the config's extrinsics, `tf_static`, with the first message) and every mask again in colour
(`mask_colour/<camera>`, a paletted PNG whose pixels are the class colours), read back with the mcap library."""

from __future__ import annotations

import io
import random

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from mcap.reader import make_reader
from PIL import Image
from scipy.spatial.transform import Rotation

from daemon.bus import pubsub
from daemon.log_format.mask_palette import UNKNOWN_CLASS_COLOUR, coloured_mask_png
from daemon.log_format.reader import read_log
from daemon.log_format.static_transforms import rpy_quaternion, sensor_frames
from daemon.spine.config import Extrinsics, load_config
from daemon.spine.messages import CameraFrame, ImuSample, SemanticMask
from daemon.spine.semantic_classes import CLASS_COLOURS
from daemon.spine.topics import IMU, TF_STATIC, camera_topic, mask_colour_topic, mask_topic
from tests.daemon.test_recorder import RecorderProcess, write_config

CAMERA = "front_wide"


def class_mask(rng: np.random.Generator, shape=(48, 64)) -> np.ndarray:
    mask = rng.integers(0, 6, size=shape, dtype=np.uint8)
    mask[:4, :4] = 0
    mask[:4, 4:8] = 5
    return mask


def png(mask: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", mask, [cv2.IMWRITE_PNG_COMPRESSION, 1])  # as the simulator encodes them
    assert ok
    return data.tobytes()


@pytest.fixture(scope="module")
def segment(tmp_path_factory):
    """A segment the real recorder wrote: camera frames, their masks and IMU samples; with the masks sent."""
    tmp_path = tmp_path_factory.mktemp("views")
    config_path = write_config(tmp_path)
    config = load_config(config_path)
    rng = np.random.default_rng(3)
    pubs = {t: pubsub.open_publisher(config, t) for t in (camera_topic(CAMERA), mask_topic(CAMERA), IMU)}
    masks = []
    try:
        rec = RecorderProcess(config_path, tmp_path / "logs")
        for k in range(10):
            pubs[camera_topic(CAMERA)].publish(CameraFrame(sensor_time_ns=k, camera=CAMERA, format="jpeg",
                                                           data=random.Random(k).randbytes(2000)))
            masks.append(class_mask(rng))
            pubs[mask_topic(CAMERA)].publish(SemanticMask(sensor_time_ns=k, camera=CAMERA, data=png(masks[-1])))
            pubs[IMU].publish(ImuSample(sensor_time_ns=k))
        rec.wait_written({mask_topic(CAMERA): 10, IMU: 10})
        assert rec.stop() == 0, rec.stderr
    finally:
        for p in pubs.values():
            p.close()
        while RecorderProcess.started:
            proc = RecorderProcess.started.pop()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        pubsub.unlink_all(config)
    [path] = sorted((tmp_path / "logs").glob("*.mcap"))
    return path, config, masks


def messages(path, topic):
    with open(path, "rb") as f:
        return [(s, c, m) for s, c, m in make_reader(f).iter_messages(topics=[topic])]


def test_every_sensor_has_a_static_transform_from_the_vehicle_frame(segment):
    path, config, _ = segment
    [(schema, channel, message)] = messages(path, TF_STATIC)
    assert schema.name == "foxglove.FrameTransforms" and channel.metadata["roadlog.type"] == "FrameTransforms"
    with open(path, "rb") as f:
        first = make_reader(f).get_summary().statistics.message_start_time
    assert message.log_time == first  # at the log's start, before every other message
    tfs = FrameTransforms()
    tfs.ParseFromString(message.data)
    by_child = {tf.child_frame_id: tf for tf in tfs.transforms}
    s = config.sensors
    assert set(by_child) == {c.name for c in s.cameras} | {"lidar", "gnss", "imu"}
    expected = {**{c.name: c.extrinsics for c in s.cameras}, "lidar": s.lidar.extrinsics,
                "gnss": Extrinsics(translation_m=s.gnss.antenna_lever_arm_m), "imu": s.gnss.imu_extrinsics}
    for name, extrinsics in expected.items():
        tf = by_child[name]
        assert tf.parent_frame_id == "vehicle"
        # stamped 0: Foxglove takes a frame's transform stamped at or before a payload's stamp, whatever its clock
        assert (tf.timestamp.seconds, tf.timestamp.nanos) == (0, 0), name
        assert (tf.translation.x, tf.translation.y, tf.translation.z) == pytest.approx(extrinsics.translation_m)
        q = tf.rotation
        rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()  # the child's axes in the parent
        assert np.allclose(rotation, extrinsics.rotation_matrix(), atol=1e-9), name
        point = np.array([1.0, 2.0, 3.0])  # a point in the sensor frame lands where the extrinsics put it
        assert np.allclose(rotation @ point + [tf.translation.x, tf.translation.y, tf.translation.z],
                           (extrinsics.matrix() @ np.append(point, 1.0))[:3])
    assert sensor_frames(config).keys() == by_child.keys()
    # the images' and fixes' frame ids are these frames
    [(_, _, frame)] = messages(path, camera_topic(CAMERA))[:1]
    image = CompressedImage()
    image.ParseFromString(frame.data)
    assert image.frame_id in by_child


def test_rpy_quaternion_follows_the_config_convention():
    rng = np.random.default_rng(1)
    for rpy in rng.uniform(-180, 180, size=(50, 3)):
        q = rpy_quaternion(*rpy)
        assert np.allclose(Rotation.from_quat(q).as_matrix(), Extrinsics(rotation_rpy_deg=tuple(rpy)).rotation_matrix())


def test_each_mask_is_logged_again_in_its_class_colours(segment):
    path, _, masks = segment
    coloured = messages(path, mask_colour_topic(CAMERA))
    originals = messages(path, mask_topic(CAMERA))
    assert len(coloured) == len(originals) == len(masks)
    for (schema, channel, message), (_, _, original), mask in zip(coloured, originals, masks, strict=True):
        assert schema.name == "foxglove.CompressedImage" and channel.metadata["roadlog.type"] == "SemanticMaskColour"
        assert message.log_time == original.log_time
        proto = CompressedImage()
        proto.ParseFromString(message.data)
        assert proto.format == "png" and proto.frame_id == CAMERA
        rgb = np.asarray(Image.open(io.BytesIO(proto.data)).convert("RGB"))  # what a viewer shows
        assert np.array_equal(rgb, CLASS_COLOURS[mask])
        assert tuple(rgb[0, 0]) == (128, 64, 128) and tuple(rgb[0, 5]) == (0, 0, 142)  # road, obstacle
        bgr = cv2.imdecode(np.frombuffer(proto.data, np.uint8), cv2.IMREAD_COLOR)  # another decoder agrees
        assert np.array_equal(bgr[..., ::-1], CLASS_COLOURS[mask])
    # the class ids themselves are untouched, and the colour channel is no message of the roadlog reader
    back = [r for r in read_log([path])]
    assert not any(r.topic.startswith("mask_colour/") for r in back)
    got = [cv2.imdecode(np.frombuffer(r.message.data, np.uint8), cv2.IMREAD_UNCHANGED) for r in back
           if r.topic == mask_topic(CAMERA)]
    assert all(np.array_equal(g, m) for g, m in zip(got, masks, strict=True))


def test_an_unknown_class_id_is_magenta_and_a_non_grey_png_has_no_colour_image():
    mask = np.full((3, 4), 200, np.uint8)
    mask[0, 0] = 1
    rgb = np.asarray(Image.open(io.BytesIO(coloured_mask_png(png(mask)))).convert("RGB"))
    assert tuple(rgb[0, 0]) == (255, 255, 255) and tuple(rgb[1, 1]) == tuple(UNKNOWN_CLASS_COLOUR)
    assert coloured_mask_png(png(np.zeros((3, 4, 3), np.uint8))) is None  # colour, not class ids
    assert coloured_mask_png(png(np.zeros((3, 4), np.uint16))) is None  # 16-bit
    assert coloured_mask_png(b"not a png") is None
