"""The `opencv` camera backend: cv2.VideoCapture on a V4L2 device, a GStreamer pipeline or a video file.

Frames are JPEG-encoded on the host (or sent raw). The sensor time is CAP_PROP_POS_MSEC: for V4L2 the
driver's buffer time stamp (CLOCK_MONOTONIC for uvcvideo), for a file its presentation time; a backend
that gives none (0 or -1 on a live device) gets the host monotonic time at read. A device that stops
delivering is reopened with a backoff; a file ends the stream at its end.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2

from daemon.spine.config import CameraConfig
from daemon.spine.health import HealthCounters
from daemon.spine.messages import CameraFrame
from drivers.camera.frame_encoding import FrameEncodingError, encode_image

BACKOFF_FIRST_S = 0.1
BACKOFF_MAX_S = 5.0


def capture_arguments(device: str) -> tuple[str | int, int]:
    """cv2.VideoCapture's (source, api): a camera index, a GStreamer pipeline ("a ! b"), a V4L2 path, a file."""
    if device.isdigit():
        return int(device), cv2.CAP_V4L2
    if "!" in device:
        return device, cv2.CAP_GSTREAMER
    if device.startswith("/dev/video"):
        return device, cv2.CAP_V4L2
    return device, cv2.CAP_ANY


def open_capture(config: CameraConfig) -> cv2.VideoCapture | None:
    source, api = capture_arguments(config.device)
    cap = cv2.VideoCapture(source, api)
    if not cap.isOpened():
        cap.release()
        return None
    if api == cv2.CAP_V4L2:
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, config.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, config.height)
        cap.set(cv2.CAP_PROP_FPS, config.rate_hz)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 2)
    return cap


def opencv_frames(config: CameraConfig, stop: threading.Event, health: HealthCounters) -> Iterator[CameraFrame]:
    """Frames from the capture until `stop` is set (or a file ends)."""
    is_file = Path(config.device).is_file()
    cap: cv2.VideoCapture | None = None
    backoff_s = BACKOFF_FIRST_S
    try:
        while not stop.is_set():
            if cap is None:
                cap = open_capture(config)
                if cap is None:
                    health.count_error(f"cannot open {config.device!r}")
                    if is_file:
                        return
                    stop.wait(backoff_s)
                    backoff_s = min(2 * backoff_s, BACKOFF_MAX_S)
                    continue
            ok, image = cap.read()
            read_ns = time.monotonic_ns()
            if not ok:
                cap.release()
                cap = None
                if is_file:
                    return
                health.count_error(f"{config.device}: no frame (device stalled or gone), reopening")
                stop.wait(backoff_s)
                backoff_s = min(2 * backoff_s, BACKOFF_MAX_S)
                continue
            backoff_s = BACKOFF_FIRST_S
            health.received += 1
            pos_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            sensor_ns = round(pos_ms * 1e6) if pos_ms > 0 or (is_file and pos_ms == 0) else read_ns
            height, width = image.shape[:2]
            if (width, height) != (config.width, config.height):
                health.count_error(f"frame is {width}x{height}, config says {config.width}x{config.height}")
            try:
                yield encode_image(image, config.name, config.encoding, config.jpeg_quality, sensor_ns)
            except FrameEncodingError as exc:
                health.count_rejected(str(exc))
    finally:
        if cap is not None:
            cap.release()
