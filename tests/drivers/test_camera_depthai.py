"""The depthai camera backend without an OAK: settings, time stamps, and the host side on real depthai messages.

What needs a device (opening it by serial, the Camera/VideoEncoder nodes, reconnecting) is not tested
here; see drivers/camera/depthai_camera.py.
"""

from __future__ import annotations

import datetime
import threading
import time

import cv2
import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from daemon.spine.config import CameraConfig  # noqa: E402
from daemon.spine.health import HealthCounters  # noqa: E402
from daemon.spine.topics import camera_topic  # noqa: E402
from drivers.camera.camera_process import run_camera_driver  # noqa: E402
from drivers.camera.depthai_camera import (  # noqa: E402
    camera_frame,
    mid_exposure_ns,
    queue_frames,
    stream_settings,
    timedelta_ns,
)
from drivers.camera.frame_encoding import raw_frame_image  # noqa: E402

W, H = 320, 240


def camera(**update) -> CameraConfig:
    base = CameraConfig(name="front_wide", backend="depthai", device="18443010D1B1A51200", width=3840, height=2160,
                        rate_hz=30, intrinsics={"fx": 1920.0, "fy": 1920.0, "cx": 1920.0, "cy": 1080.0},
                        extrinsics={}, encoding="h265", jpeg_quality=80)
    return base.model_copy(update=update)


def test_stream_settings_follow_the_config():
    h265 = stream_settings(camera())
    assert h265.size == (3840, 2160) and h265.fps == 30
    assert h265.profile == dai.VideoEncoderProperties.Profile.H265_MAIN and h265.frame_type == dai.ImgFrame.Type.NV12
    assert h265.keyframe_frequency == 30
    mjpeg = stream_settings(camera(encoding="jpeg", rate_hz=12.5, jpeg_quality=70))
    assert mjpeg.profile == dai.VideoEncoderProperties.Profile.MJPEG and mjpeg.quality == 70
    assert mjpeg.keyframe_frequency == 12
    raw = stream_settings(camera(encoding="raw"))
    assert raw.profile is None and raw.frame_type == dai.ImgFrame.Type.BGR888i


def test_timedelta_to_ns_is_exact():
    assert timedelta_ns(datetime.timedelta(days=3, seconds=86399, microseconds=999_999)) == \
        (3 * 86400 + 86399) * 10**9 + 999_999_000
    assert timedelta_ns(datetime.timedelta(microseconds=-1)) == -1000


def test_mid_exposure_agrees_with_depthai():
    frame = dai.ImgFrame()
    frame.setTimestamp(datetime.timedelta(seconds=1234, microseconds=567_891))
    settings = frame.cam
    settings.exposureTimeUs = 8_330
    frame.cam = settings
    assert mid_exposure_ns(frame) == timedelta_ns(frame.getTimestamp(dai.CameraExposureOffset.MIDDLE))
    assert mid_exposure_ns(frame) == 1234_567_891_000 - 4_165_000


def encoded(seq: int, ts: datetime.timedelta, payload: bytes, exposure_us: int = 10_000) -> dai.EncodedFrame:
    frame = dai.EncodedFrame()
    frame.setSequenceNum(seq)
    frame.setTimestamp(ts)
    frame.setData(list(payload))
    settings = frame.cam
    settings.exposureTimeUs = exposure_us
    frame.cam = settings
    return frame


def test_encoded_frames_from_a_queue_with_sequence_gaps():
    config = camera()
    queue = dai.MessageQueue("frames", 64, True)
    now = time.monotonic()
    seqs = [0, 1, 2, 5, 6, 7, 9]  # 2 gaps, 3 frames lost on the device
    for k, seq in enumerate(seqs):
        queue.send(encoded(seq, datetime.timedelta(seconds=now + seq / 30), bytes([0, 0, 0, 1, 0x26, k])))
    queue.send(dai.ImgDetections())  # not a frame: counted, skipped
    stop = threading.Event()
    threading.Timer(0.5, queue.close).start()
    health = HealthCounters("camera_front_wide")
    published: list = []
    run_camera_driver(config, queue_frames(queue, config, stop, health), lambda t, m: published.append((t, m)),
                      stop, health, health_period_s=0.1)
    frames = [m for t, m in published if t == camera_topic("front_wide")]
    assert len(frames) == len(seqs)
    assert all(f.format == "h265" and f.width == 0 and f.camera == "front_wide" for f in frames)
    assert [f.data for f in frames] == [bytes([0, 0, 0, 1, 0x26, k]) for k in range(len(seqs))]
    expected = [timedelta_ns(datetime.timedelta(seconds=now + s / 30)) - 5_000_000 for s in seqs]
    assert [f.sensor_time_ns for f in frames] == expected
    assert health.sequence_gaps == 2 and health.dropped == 3 and health.rejected == 1
    assert health.received == len(seqs) and health.published == len(seqs)


def test_raw_frames_through_a_host_only_pipeline(tmp_path):
    """A real depthai pipeline (host only: ReplayVideo) feeding the backend's host side."""
    video = str(tmp_path / "oak.mp4")
    writer = cv2.VideoWriter(video, cv2.VideoWriter_fourcc(*"mp4v"), 10, (W, H))
    for i in range(8):
        image = np.full((H, W, 3), 30, np.uint8)
        image[:, 30 * i: 30 * i + 30] = 230
        writer.write(image)
    writer.release()
    config = camera(encoding="raw", width=W, height=H, rate_hz=10,
                    intrinsics={"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0})
    pipeline = dai.Pipeline(False)
    replay = pipeline.create(dai.node.ReplayVideo)
    replay.setReplayVideoFile(video)
    replay.setOutFrameType(stream_settings(config).frame_type)
    replay.setLoop(False)
    replay.setFps(config.rate_hz)
    queue = replay.out.createOutputQueue(maxSize=4, blocking=True)
    published: list = []
    stop = threading.Event()
    health = HealthCounters("camera_front_wide")
    pipeline.start()
    try:
        run_camera_driver(config, queue_frames(queue, config, stop, health),
                          lambda t, m: published.append((t, m, time.monotonic_ns())), stop, health)
    finally:
        pipeline.stop()
    frames = [(m, at) for t, m, at in published if t == camera_topic("front_wide")]
    assert len(frames) == 8 and health.sequence_gaps == 0
    for i, (f, at) in enumerate(frames):
        assert f.format == "bgr8" and (f.width, f.height) == (W, H)
        image = raw_frame_image(f)
        assert int(np.argmax(image[H // 2, :240, 1].reshape(-1, 30).mean(axis=1))) == i
        # On the host's monotonic clock (not the device's or UTC): received after it was stamped, within a
        # second (a loaded CI machine delayed one frame 113 ms; a clock mix-up would be off by hours).
        assert 0 <= at - f.sensor_time_ns < 1_000_000_000
    stamps = np.diff([f.sensor_time_ns for f, _ in frames]) / 1e6
    assert np.median(stamps) == pytest.approx(100, abs=10)


def test_camera_frame_of_an_encoded_packet_keeps_the_bitstream():
    packet = encoded(3, datetime.timedelta(seconds=10), b"\xff\xd8jpeg\xff\xd9", exposure_us=0)
    frame = camera_frame(packet, camera(encoding="jpeg"))
    assert frame.format == "jpeg" and frame.data == b"\xff\xd8jpeg\xff\xd9" and frame.sensor_time_ns == 10**10
