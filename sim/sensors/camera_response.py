"""A simulated camera's photometric response: exposure and gain, white balance, saturation, vignetting,
gamma, sensor noise, and the JPEG a car's camera delivers."""

from __future__ import annotations

import cv2
import numpy as np

from daemon.spine.config import CameraPhotometry

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
ZERO = (0.0, 0.0, 0.0, 0.0)
ONE = (1.0, 1.0, 1.0, 1.0)


def vignetting_map(width: int, height: int, cx: float, cy: float, strength: float) -> np.ndarray:
    """Relative illumination (H, W, 3): 1 at the principal point, 1 - strength at the farthest corner."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32) + 0.5, np.arange(height, dtype=np.float32) + 0.5)
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    falloff = (1.0 - strength * r2 / r2.max()).astype(np.float32)
    return np.repeat(falloff[..., None], 3, axis=2)


def colour_matrix(photometry: CameraPhotometry, exposure: float) -> np.ndarray:
    """3x3 matrix applying exposure, gain and white balance, then saturation about the luma."""
    s = photometry.saturation
    saturate = s * np.eye(3) + (1.0 - s) * np.outer(np.ones(3), LUMA)
    wb = np.diag(np.asarray(photometry.white_balance) * exposure * photometry.gain)
    return (saturate @ wb).astype(np.float32)


def expose(radiance: np.ndarray, photometry: CameraPhotometry, vignette: np.ndarray, exposure: float,
           noise_scale: float, seed: int) -> np.ndarray:
    """Scene radiance (H, W, 3) -> the camera's 8-bit RGB image (noise drawn from OpenCV's RNG, seeded)."""
    x = cv2.transform(radiance, colour_matrix(photometry, exposure))
    x = cv2.multiply(x, vignette)
    x = cv2.min(cv2.max(x, ZERO), ONE)  # (a bare float would be a scalar for the first channel only)
    x = cv2.pow(x, 1.0 / (2.2 * photometry.gamma))
    sigma = photometry.noise_sigma * noise_scale
    out = np.empty(radiance.shape, np.uint8)
    if sigma > 0:
        noise = np.empty(radiance.shape, np.float32)
        cv2.setRNGSeed(seed)
        cv2.randn(noise, (0.0, 0.0, 0.0), (sigma, sigma, sigma))
        cv2.scaleAdd(x, 255.0, noise, dst=noise)
        cv2.convertScaleAbs(cv2.max(noise, ZERO), dst=out)
    else:
        cv2.convertScaleAbs(x, dst=out, alpha=255.0)
    return out


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return data.tobytes()
