"""The live map's images on disk: north-up PNGs and JSON written atomically (a reader never sees half a file), the
semantic colours."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from daemon.spine.semantic_classes import CLASS_COLOURS
from mapping.method.road_map import NO_LABEL


def atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def north_up_png(rgb: np.ndarray, what: str) -> bytes:
    """A bird's-eye RGB raster (row 0 south) as PNG bytes, north up."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(np.flipud(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"cannot encode {what}")
    return data.tobytes()


def atomic_png(path: Path, rgb: np.ndarray) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(north_up_png(rgb, path.name))
    os.replace(tmp, path)


def semantic_image(labels: np.ndarray) -> np.ndarray:
    return CLASS_COLOURS[np.minimum(labels, len(CLASS_COLOURS) - 1)] * (labels != NO_LABEL)[..., None].astype(np.uint8)

