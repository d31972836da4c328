"""The opencv camera backend on a real video file (written with cv2.VideoWriter) through run_camera_driver."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from daemon.spine.config import CameraConfig, ConfigError
from daemon.spine.health import HealthCounters
from daemon.spine.messages import CameraFrame, DriverHealth
from daemon.spine.topics import camera_topic, health_topic
from drivers.camera.camera_driver import open_frame_source
from drivers.camera.camera_process import run_camera_driver
from drivers.camera.frame_encoding import encode_image, raw_frame_image
from drivers.camera.opencv_camera import capture_arguments

W, H, RATE, N = 320, 240, 10, 25


def pattern_image(i: int) -> np.ndarray:
    """Frame i: a dark textured background and a white block whose column says i."""
    image = np.random.default_rng(i).integers(0, 80, (H, W, 3), dtype=np.uint8)
    image[100:140, 10 * i + 5: 10 * i + 15] = 255
    return image


def block_column(image: np.ndarray) -> int:
    profile = image[100:140].mean(axis=(0, 2))
    return int(np.argmax(np.convolve(profile, np.ones(10), "valid"))) // 10


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> str:
    path = str(tmp_path_factory.mktemp("video") / "drive.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), RATE, (W, H))
    assert writer.isOpened()
    for i in range(N):
        writer.write(pattern_image(i))
    writer.release()
    return path


def camera(device: str, **update) -> CameraConfig:
    base = CameraConfig(name="front", backend="opencv", device=device, width=W, height=H, rate_hz=RATE,
                        intrinsics={"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0}, extrinsics={},
                        encoding="jpeg", jpeg_quality=85)
    return base.model_copy(update=update)


def drive(config: CameraConfig, stop: threading.Event | None = None, health_period_s: float = 0.05):
    stop = stop or threading.Event()
    published: list[tuple[str, object]] = []
    health = HealthCounters("camera_front", expected_rate_hz=config.rate_hz)
    frames = open_frame_source(config, stop, health)
    run_camera_driver(config, frames, lambda t, m: published.append((t, m)), stop, health,
                      health_period_s=health_period_s)
    return published, health


def test_frames_timestamps_and_counts_from_a_video_file(video):
    published, health = drive(camera(video))
    frames = [m for t, m in published if t == camera_topic("front")]
    assert len(frames) == N and all(isinstance(f, CameraFrame) for f in frames)
    assert all(f.format == "jpeg" and f.camera == "front" and f.width == 0 for f in frames)
    assert [f.sensor_time_ns for f in frames] == [i * 100_000_000 for i in range(N)]  # CAP_PROP_POS_MSEC
    for i, f in enumerate(frames):
        image = cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (H, W, 3)
        assert block_column(image) == i
    assert health.received == N and health.published == N and health.errors == 0
    last = [m for t, m in published if t == health_topic("camera_front")][-1]
    assert isinstance(last, DriverHealth) and last.published == N and last.process == "camera_front"


def test_jpeg_quality_is_the_configured_one(video):
    small = [m for t, m in drive(camera(video, jpeg_quality=30))[0] if t == camera_topic("front")]
    large = [m for t, m in drive(camera(video, jpeg_quality=95))[0] if t == camera_topic("front")]
    assert sum(len(f.data) for f in small) < 0.6 * sum(len(f.data) for f in large)


def test_raw_frames_carry_their_size(video):
    frames = [m for t, m in drive(camera(video, encoding="raw"))[0] if t == camera_topic("front")]
    assert len(frames) == N
    assert all(f.format == "bgr8" and (f.width, f.height) == (W, H) and len(f.data) == W * H * 3 for f in frames)
    assert block_column(raw_frame_image(frames[7])) == 7


def test_a_size_other_than_the_configured_one_is_counted(video):
    published, health = drive(camera(video, width=640, height=480, intrinsics={"fx": 1, "fy": 1, "cx": 0, "cy": 0}))
    assert health.errors == N and "320x240" in health.last_error
    assert sum(t == camera_topic("front") for t, _ in published) == N


def test_a_missing_device_is_retried_with_backoff_not_fatal():
    stop = threading.Event()
    timer = threading.Timer(0.8, stop.set)
    timer.start()
    t0 = time.monotonic()
    published, health = drive(camera("/dev/video_roadlog_missing"), stop=stop, health_period_s=0.2)
    assert time.monotonic() - t0 < 3
    assert 2 <= health.errors <= 5  # 0.1, 0.2, 0.4 s backoff
    assert "cannot open" in health.last_error
    states = [m.state for t, m in published if t == health_topic("camera_front")]
    assert states and states[-1] == "error"


def test_png_frames_are_lossless_and_mono8_frames_grey(video):
    published = drive(camera(video, encoding="png"))[0]
    png = [m for t, m in published if t == camera_topic("front")]
    assert len(png) == N and all(f.format == "png" and f.width == 0 for f in png)
    decoded = [cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_UNCHANGED) for f in png]
    raw = [m for t, m in drive(camera(video, encoding="raw"))[0] if t == camera_topic("front")]
    assert all(np.array_equal(d, raw_frame_image(r)) for d, r in zip(decoded, raw, strict=True))  # lossless
    mono = [m for t, m in drive(camera(video, encoding="mono8"))[0] if t == camera_topic("front")]
    assert all(f.format == "mono8" and (f.width, f.height) == (W, H) and len(f.data) == W * H for f in mono)
    grey = raw_frame_image(mono[9])
    assert grey.shape == (H, W) and np.array_equal(grey, cv2.cvtColor(raw_frame_image(raw[9]), cv2.COLOR_BGR2GRAY))
    assert block_column(grey[:, :, None]) == 9


@pytest.mark.parametrize("backend, encoding", [("opencv", "h265"), ("depthai", "png"), ("depthai", "mono8")])
def test_encodings_a_backend_cannot_deliver_are_a_config_error(backend, encoding):
    fields = camera("0").model_dump() | {"backend": backend, "encoding": encoding}
    with pytest.raises(ValidationError, match=f"the {backend} backend delivers .*not {encoding}"):
        CameraConfig.model_validate(fields)


def test_a_recorded_camera_has_no_live_driver():
    config = CameraConfig.model_validate(camera("").model_dump() | {"backend": "recorded", "encoding": "png"})
    with pytest.raises(ConfigError, match="no live driver"):
        open_frame_source(config, threading.Event(), HealthCounters("camera_front"))


def test_capture_arguments():
    assert capture_arguments("0") == (0, cv2.CAP_V4L2)
    assert capture_arguments("/dev/video2") == ("/dev/video2", cv2.CAP_V4L2)
    pipeline = "v4l2src device=/dev/video0 ! videoconvert ! appsink"
    assert capture_arguments(pipeline) == (pipeline, cv2.CAP_GSTREAMER)
    assert capture_arguments("/tmp/x.mp4") == ("/tmp/x.mp4", cv2.CAP_ANY)


def test_encode_image_mono_and_bad_input():
    mono = np.arange(W * H, dtype=np.uint32).astype(np.uint8).reshape(H, W)
    frame = encode_image(mono, "c", "raw", 90, 5)
    assert frame.format == "mono8" and np.array_equal(raw_frame_image(frame), mono)
    with pytest.raises(ValueError):
        encode_image(np.zeros((0, 0, 3), np.uint8), "c", "jpeg", 90, 5)
