"""The live map's images on disk: north-up PNGs and JSON written atomically (a reader never sees half a file), a
window's previews (coloured by mapping.outputs.map_colours)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from mapping.outputs.map_colours import elevation_image, semantic_image

PREVIEW_NAMES = ("rgb", "semantics", "elevation")


def atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def png_bytes(image: np.ndarray, what: str) -> bytes:
    """An RGB image (row 0 the top) as PNG bytes."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"cannot encode {what}")
    return data.tobytes()


def north_up_png(rgb: np.ndarray, what: str) -> bytes:
    """A bird's-eye RGB raster (row 0 south) as PNG bytes, north up."""
    return png_bytes(np.flipud(rgb), what)


def atomic_png(path: Path, rgb: np.ndarray, north_up: bool = False) -> None:
    """A bird's-eye RGB raster (row 0 south) as a north-up PNG; `north_up`: `rgb` is an image already (row 0
    the top), written as it is."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(png_bytes(rgb, path.name) if north_up else north_up_png(rgb, path.name))
    os.replace(tmp, path)


def preview_images(bev: dict, camera: str, semantics: bool) -> dict[str, np.ndarray]:
    """A window's previews from its BEV rasters (map_export.bev_rasters): `camera`'s colour, the semantics (left
    out when the window has none) and the elevation."""
    images = {"rgb": bev["rgb"][camera], "semantics": semantic_image(bev["labels"]),
              "elevation": elevation_image(bev["elevation"])}
    if not semantics:
        del images["semantics"]
    return images


def write_previews(folder: Path, images: dict[str, np.ndarray]) -> None:
    """The previews as `<name>.png` in `folder`; one left out is removed (not an older window's left behind)."""
    for name in PREVIEW_NAMES:
        if name in images:
            atomic_png(folder / f"{name}.png", images[name])
        else:
            (folder / f"{name}.png").unlink(missing_ok=True)
