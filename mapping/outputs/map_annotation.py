"""The maps' annotated PNGs (`*_annotated.png`) for people to look at: the north-up raster (enlarged when small)
beside a panel with its legend (semantic classes) or colour bar (elevation, metres), a scale bar and a north arrow.
The plain PNGs stay one pixel per cell, as the GeoTIFFs and .npy grids."""

from __future__ import annotations

import math

import cv2
import numpy as np

from daemon.spine.semantic_classes import CLASS_COLOURS, MAP_CLASSES
from mapping.outputs.map_colours import viridis_rgb

MIN_MAP_PX = 480  # a small map is enlarged (whole pixels per cell) until its longer side reaches this
PANEL_W, PANEL_MIN_H = 230, 470
FONT, INK, PAPER = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0), (255, 255, 255)
NOT_MAPPED = "black: not mapped"


def _text(img: np.ndarray, text: str, x: int, y: int, scale: float = 0.45, thickness: int = 1) -> None:
    cv2.putText(img, text, (x, y), FONT, scale, INK, thickness, cv2.LINE_AA)


def nice_length_m(max_m: float) -> float:
    """The longest 1, 2 or 5 x 10^k metres not above `max_m`."""
    k = 10.0 ** math.floor(math.log10(max_m))
    return max(f * k for f in (1.0, 2.0, 5.0) if f * k <= max_m)


def _north_arrow(panel: np.ndarray, x: int, y: int) -> int:
    """An arrow pointing up (north: the map's row 0 is its northern edge), its top at y; the y below it."""
    pts = np.array([[x, y + 8], [x - 12, y + 48], [x, y + 38], [x + 12, y + 48]], np.int32)
    cv2.fillPoly(panel, [pts], INK, cv2.LINE_AA)
    _text(panel, "N", x - 7, y + 70, 0.6, 2)
    _text(panel, "x east, y north (ENU)", x + 22, y + 36, 0.38)
    return y + 82


def _scale_bar(panel: np.ndarray, x: int, y: int, px_per_m: float) -> int:
    length_m = nice_length_m((PANEL_W - 2 * x - 24) / px_per_m)  # room for its label centred on its end
    length_px = int(round(length_m * px_per_m))
    cv2.rectangle(panel, (x, y), (x + length_px, y + 6), INK, -1)
    cv2.rectangle(panel, (x + length_px // 2, y + 1), (x + length_px - 1, y + 5), PAPER, -1)  # half white
    label = f"{length_m:g} m" if length_m >= 1 else f"{length_m * 100:g} cm"
    _text(panel, "0", x - 4, y + 24)
    width = cv2.getTextSize(label, FONT, 0.45, 1)[0][0]
    _text(panel, label, x + length_px - width // 2, y + 24)
    return y + 34


def _legend(panel: np.ndarray, x: int, y: int) -> int:
    for c in MAP_CLASSES:
        cv2.rectangle(panel, (x, y), (x + 18, y + 14), tuple(int(v) for v in CLASS_COLOURS[c]), -1)
        cv2.rectangle(panel, (x, y), (x + 18, y + 14), INK, 1)
        _text(panel, c.name.lower().replace("_", " "), x + 26, y + 12)
        y += 22
    _text(panel, NOT_MAPPED, x, y + 12, 0.4)
    return y + 24


def _colour_bar(panel: np.ndarray, x: int, y: int, lo_m: float, hi_m: float) -> int:
    h, w = 160, 20
    ramp = viridis_rgb(np.linspace(1, 0, h))  # top: the high end
    panel[y:y + h, x:x + w] = ramp[:, None, :]
    cv2.rectangle(panel, (x, y), (x + w, y + h), INK, 1)
    for frac in (0.0, 0.5, 1.0):
        ty = int(round(y + (1 - frac) * (h - 1)))
        cv2.line(panel, (x + w, ty), (x + w + 5, ty), INK, 1)
        _text(panel, f"{lo_m + frac * (hi_m - lo_m):.2f} m", x + w + 9, ty + 5)
    _text(panel, "height above the ENU", x, y + h + 18, 0.38)
    _text(panel, "frame's origin, m;", x, y + h + 33, 0.38)
    _text(panel, "saturates past 1-99 %", x, y + h + 48, 0.38)
    _text(panel, NOT_MAPPED, x, y + h + 66, 0.4)
    return y + h + 76


def annotated_map(raster: np.ndarray, resolution_m: float, title: str, *, legend: bool = False,
                  elevation_range_m: tuple[float, float] | None = None) -> np.ndarray:
    """A bird's-eye RGB raster (H, W, 3; row 0 south, as the maps' rasters) as an image, north up, with a panel
    on its right: `title`, the semantic legend (`legend`) or an elevation colour bar over `elevation_range_m`, a
    north arrow and a scale bar. RGB uint8, row 0 the top."""
    rgb = np.flipud(raster)
    h, w = rgb.shape[:2]
    zoom = max(1, MIN_MAP_PX // max(h, w, 1))
    shown = np.repeat(np.repeat(rgb, zoom, 0), zoom, 1) if zoom > 1 else rgb
    out_h = max(shown.shape[0], PANEL_MIN_H)
    out = np.full((out_h, shown.shape[1] + PANEL_W, 3), 255, np.uint8)
    out[:shown.shape[0], :shown.shape[1]] = shown
    panel = out[:, shown.shape[1]:]
    cv2.line(panel, (0, 0), (0, out_h - 1), INK, 1)
    x = 14
    _text(panel, title, x, 24, 0.55, 1)
    _text(panel, f"{resolution_m * 100:g} cm cells", x, 44, 0.4)
    y = 62
    if legend:
        y = _legend(panel, x, y)
    if elevation_range_m is not None:
        y = _colour_bar(panel, x, y, *elevation_range_m)
    y = _north_arrow(panel, x + 12, y + 4)
    _scale_bar(panel, x, y + 8, zoom / resolution_m)
    return out
