"""The maps' colours: elevation through OpenCV's viridis colour map (low purple, high yellow) over a robust range,
as RGB; the semantic classes through CLASS_COLOURS."""

from __future__ import annotations

import cv2
import numpy as np

from daemon.spine.semantic_classes import CLASS_COLOURS
from mapping.method.road_map import NO_LABEL

ELEVATION_PERCENTILES = (1, 99)  # the colour range: outliers saturate instead of washing the map out


def viridis_rgb(scaled: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 RGB of values in [0, 1] (0: the map's low end, purple; 1: its high end, yellow)."""
    index = (np.clip(np.nan_to_num(scaled), 0, 1) * 255 + 0.5).astype(np.uint8)
    bgr = cv2.applyColorMap(index.reshape(-1, 1), cv2.COLORMAP_VIRIDIS)  # OpenCV's colour maps are BGR
    return bgr[:, 0, ::-1].reshape(index.shape + (3,))


def elevation_range(elevation: np.ndarray) -> tuple[float, float] | None:
    """The elevations (m) the colour map's ends stand for (ELEVATION_PERCENTILES), None with no valid cell."""
    valid = np.isfinite(elevation)
    if not valid.any():
        return None
    lo, hi = np.percentile(elevation[valid], ELEVATION_PERCENTILES)
    return float(lo), float(max(hi, lo + 1e-6))


def elevation_image(elevation: np.ndarray) -> np.ndarray:
    """RGB of an elevation raster (NaN: not mapped, black), coloured over elevation_range."""
    out = np.zeros(elevation.shape + (3,), np.uint8)
    span = elevation_range(elevation)
    if span is not None:
        valid = np.isfinite(elevation)
        out[valid] = viridis_rgb((elevation[valid] - span[0]) / (span[1] - span[0]))
    return out


def semantic_image(labels: np.ndarray) -> np.ndarray:
    """RGB of a class-id raster (NO_LABEL: black)."""
    return CLASS_COLOURS[np.minimum(labels, len(CLASS_COLOURS) - 1)] * (labels != NO_LABEL)[..., None].astype(np.uint8)
