"""A simulated camera's photometric response: exposure and gain, white balance, saturation, vignetting,
gamma, sensor noise, and the JPEG a car's camera delivers."""

from __future__ import annotations

import cv2
import numpy as np

from daemon.config import CameraPhotometry

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
LUT_SIZE = 4096


def vignetting_map(width: int, height: int, cx: float, cy: float, strength: float) -> np.ndarray:
    """Relative illumination (H, W, 1): 1 at the principal point, 1 - strength at the farthest corner."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32) + 0.5, np.arange(height, dtype=np.float32) + 0.5)
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    return (1.0 - strength * r2 / r2.max())[..., None].astype(np.float32)


def tone_lut(gamma: float) -> np.ndarray:
    """Linear exposure 0..1 (LUT_SIZE steps) -> 8-bit value, sRGB-like 1/2.2 power scaled by gamma."""
    x = np.linspace(0.0, 1.0, LUT_SIZE, dtype=np.float64)
    return (255.0 * x ** (1.0 / (2.2 * gamma))).astype(np.float32)


def expose(radiance: np.ndarray, photometry: CameraPhotometry, vignette: np.ndarray, lut: np.ndarray,
           exposure: float, noise_scale: float, rng: np.random.Generator) -> np.ndarray:
    """Scene radiance (H, W, 3) -> the camera's 8-bit RGB image."""
    wb = np.asarray(photometry.white_balance, np.float32) * np.float32(exposure * photometry.gain)
    x = radiance * wb
    if photometry.saturation != 1.0:
        y = (x @ LUMA)[..., None]
        x = y + np.float32(photometry.saturation) * (x - y)
    x *= vignette
    index = np.clip(x * (LUT_SIZE - 1), 0, LUT_SIZE - 1).astype(np.int16)
    value = lut[index]
    sigma = photometry.noise_sigma * noise_scale
    if sigma > 0:
        value += rng.standard_normal(value.shape, dtype=np.float32) * np.float32(sigma)
    return np.clip(value + 0.5, 0, 255).astype(np.uint8)


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return data.tobytes()
