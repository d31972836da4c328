"""The `depthai` camera backend: a Luxonis OAK (depthai 3.x) picked by serial number, encoding on the device.

The pipeline: Camera (socket CAM_A) -> an NV12 output at the configured size and rate -> VideoEncoder
(MJPEG at the configured quality, H.264 or H.265 main profile with a one-second GOP); encoding "raw"
skips the encoder and sends BGR888i frames. Frames carry the camera's time stamps, which depthai keeps
on the host's time.monotonic() clock: `getTimestamp()` is the end of exposure, and the sensor time
published is mid-exposure (`getTimestamp() - getExposureTime() / 2`, as ImgFrame's
CameraExposureOffset.MIDDLE). Gaps in the device's frame sequence numbers are counted.

Tested here without a device: the stream settings, the time-stamp conversion, and the host side
(`queue_frames`) on real depthai messages, incl. a host-only pipeline (ReplayVideo) for raw frames.
Not tested (needs an OAK): opening the device by serial, `build_device_pipeline` (Camera and
VideoEncoder are device nodes, which a host-only pipeline refuses), on-device encoding, and
reconnecting after the device is lost.
"""

from __future__ import annotations

import datetime
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import depthai as dai
import numpy as np

from daemon.spine.config import CameraConfig
from daemon.spine.health import HealthCounters
from daemon.spine.messages import CameraFrame

BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 10.0
QUEUE_SIZE = 8
POLL_S = 0.1


@dataclass(frozen=True)
class StreamSettings:
    """What the device is asked for, derived from the camera config."""

    size: tuple[int, int]
    fps: float
    frame_type: dai.ImgFrame.Type
    profile: dai.VideoEncoderProperties.Profile | None  # None: raw frames, no encoder
    quality: int
    keyframe_frequency: int


_PROFILES = {
    "jpeg": dai.VideoEncoderProperties.Profile.MJPEG,
    "h264": dai.VideoEncoderProperties.Profile.H264_MAIN,
    "h265": dai.VideoEncoderProperties.Profile.H265_MAIN,
    "raw": None,
}


def stream_settings(config: CameraConfig) -> StreamSettings:
    profile = _PROFILES[config.encoding]
    return StreamSettings(
        size=(config.width, config.height),
        fps=config.rate_hz,
        frame_type=dai.ImgFrame.Type.BGR888i if profile is None else dai.ImgFrame.Type.NV12,
        profile=profile,
        quality=config.jpeg_quality,
        keyframe_frequency=max(1, round(config.rate_hz)),
    )


def timedelta_ns(td: datetime.timedelta) -> int:
    """A timedelta as integer nanoseconds, exactly (no float round trip)."""
    return ((td.days * 86400 + td.seconds) * 1_000_000 + td.microseconds) * 1000


def mid_exposure_ns(packet: dai.ImgFrame | dai.EncodedFrame) -> int:
    """Mid-exposure time of a frame on the host monotonic clock, in ns."""
    return timedelta_ns(packet.getTimestamp()) - timedelta_ns(packet.getExposureTime()) // 2


def camera_frame(packet: dai.ImgFrame | dai.EncodedFrame, config: CameraConfig) -> CameraFrame:
    """The CameraFrame of one device message: the encoder's bitstream, or raw BGR pixels."""
    data = bytes(np.asarray(packet.getData(), dtype=np.uint8))
    if isinstance(packet, dai.EncodedFrame):
        return CameraFrame(sensor_time_ns=mid_exposure_ns(packet), camera=config.name, format=config.encoding,
                           data=data)
    return CameraFrame(sensor_time_ns=mid_exposure_ns(packet), camera=config.name, format="bgr8",
                       width=packet.getWidth(), height=packet.getHeight(), data=data)


def build_device_pipeline(pipeline: dai.Pipeline, config: CameraConfig) -> dai.MessageQueue:
    """Add the camera (and encoder) nodes to a device pipeline; return the host queue of its frames."""
    s = stream_settings(config)
    cam = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
    out = cam.requestOutput(s.size, type=s.frame_type, fps=s.fps)
    if s.profile is not None:
        encoder = pipeline.create(dai.node.VideoEncoder).build(
            out, frameRate=s.fps, profile=s.profile, keyframeFrequency=s.keyframe_frequency, quality=s.quality)
        out = encoder.out
    return out.createOutputQueue(maxSize=QUEUE_SIZE, blocking=False)


def queue_frames(queue: dai.MessageQueue, config: CameraConfig, stop: threading.Event,
                 health: HealthCounters) -> Iterator[CameraFrame]:
    """Frames from a running pipeline's queue until `stop` is set or the queue closes."""
    last_seq: int | None = None
    while not stop.is_set():
        try:
            packet = queue.get(datetime.timedelta(seconds=POLL_S))
        except dai.MessageQueue.QueueException:  # the pipeline stopped and closed its queues
            return
        if packet is None:
            continue
        if not isinstance(packet, (dai.ImgFrame, dai.EncodedFrame)):
            health.count_rejected(f"unexpected {type(packet).__name__} on the frame queue")
            continue
        health.received += 1
        seq = packet.getSequenceNum()
        if last_seq is not None and seq != last_seq + 1:
            health.sequence_gaps += 1
            health.dropped += max(0, seq - last_seq - 1)
        last_seq = seq
        yield camera_frame(packet, config)


def open_device(serial: str) -> dai.Device:
    """The OAK with this serial number (device ID), or the first one found when `serial` is empty."""
    return dai.Device(dai.DeviceInfo(serial)) if serial else dai.Device()


def depthai_frames(config: CameraConfig, stop: threading.Event, health: HealthCounters) -> Iterator[CameraFrame]:
    """Frames from the OAK until `stop` is set; a lost device is reopened with a backoff."""
    backoff_s = BACKOFF_FIRST_S
    while not stop.is_set():
        try:
            device = open_device(config.device)
            pipeline = dai.Pipeline(device)
            queue = build_device_pipeline(pipeline, config)
            pipeline.start()
        except RuntimeError as exc:
            health.count_error(f"OAK {config.device or '(any)'}: {exc}")
            stop.wait(backoff_s)
            backoff_s = min(2 * backoff_s, BACKOFF_MAX_S)
            continue
        backoff_s = BACKOFF_FIRST_S
        try:
            yield from queue_frames(queue, config, stop, health)
        finally:
            pipeline.stop()
            device.close()
        if not stop.is_set():
            health.count_error(f"OAK {config.device or '(any)'}: pipeline stopped, reconnecting")
