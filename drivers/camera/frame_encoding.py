"""A camera image (numpy, BGR or mono) -> the CameraFrame the car logs: JPEG, PNG (lossless), or raw pixels (as
captured, or mono8: converted to grey)."""

from __future__ import annotations

import cv2
import numpy as np

from daemon.spine.messages import RAW_FORMAT_CHANNELS, CameraFrame


class FrameEncodingError(ValueError):
    """An image that cannot be encoded (empty, wrong shape, encoder failure)."""


def encode_image(image: np.ndarray, camera: str, encoding: str, jpeg_quality: int, sensor_time_ns: int) -> CameraFrame:
    """`encoding` is "jpeg" (cv2.imencode at `jpeg_quality`), "png" (cv2.imencode, lossless), "raw" (bgr8 / mono8
    bytes with the size) or "mono8" (grey bytes with the size; a colour image is converted)."""
    if image is None or image.size == 0 or image.dtype != np.uint8 or image.ndim not in (2, 3) or (
            image.ndim == 3 and image.shape[2] not in (1, 3)):
        shape = None if image is None else (image.shape, image.dtype)
        raise FrameEncodingError(f"cannot encode an image of shape/dtype {shape}")
    height, width = image.shape[:2]
    if encoding in ("jpeg", "png"):
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if encoding == "jpeg" else []
        ok, buf = cv2.imencode(".jpg" if encoding == "jpeg" else ".png", image, params)
        if not ok:
            raise FrameEncodingError("cv2.imencode failed")
        return CameraFrame(sensor_time_ns=sensor_time_ns, camera=camera, format=encoding, data=buf.tobytes())
    if encoding == "mono8":
        grey = image if image.ndim == 2 or image.shape[2] == 1 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return CameraFrame(sensor_time_ns=sensor_time_ns, camera=camera, format="mono8", width=width, height=height,
                           data=np.ascontiguousarray(grey).tobytes())
    if encoding == "raw":
        mono = image.ndim == 2 or image.shape[2] == 1
        return CameraFrame(sensor_time_ns=sensor_time_ns, camera=camera, format="mono8" if mono else "bgr8",
                           width=width, height=height, data=np.ascontiguousarray(image).tobytes())
    raise FrameEncodingError(f"encoding {encoding!r} is not done on the host (jpeg, png, raw or mono8)")


def raw_frame_image(frame: CameraFrame) -> np.ndarray:
    """The pixels of a raw (rgb8, bgr8, mono8) frame as a BGR or mono image."""
    channels = RAW_FORMAT_CHANNELS.get(frame.format)
    if channels is None:
        raise FrameEncodingError(f"{frame.format!r} is not a raw format")
    expected = frame.width * frame.height * channels
    if len(frame.data) != expected:
        raise FrameEncodingError(f"{frame.format} {frame.width}x{frame.height}: {len(frame.data)} bytes, "
                                 f"expected {expected}")
    image = np.frombuffer(frame.data, np.uint8).reshape(frame.height, frame.width, channels)
    if frame.format == "rgb8":
        return image[:, :, ::-1]
    return image[:, :, 0] if channels == 1 else image
