"""The map's rasters as GeoTIFFs a GIS opens in place: elevation (float32 m, NaN nodata), semantics (uint8 class
ids with a colour table, NO_LABEL nodata), RGB per camera (a mask of the mapped cells), north up, in a transverse
Mercator centred at the local frame's origin (local_crs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import Affine

from daemon.spine.local_frame import WGS84_A, WGS84_E2, LocalFrame
from daemon.spine.semantic_classes import CLASS_COLOURS, SemanticClass
from mapping.method.road_map import NO_LABEL

ROWS_PER_WRITE = 1024  # rasters are written in blocks of rows: a large map's (memory-mapped) .npy is never all read
_PROFILE = {"driver": "GTiff", "compress": "deflate", "tiled": True, "blockxsize": 256, "blockysize": 256,
            "bigtiff": "IF_SAFER"}  # BigTIFF where the raster could pass 4 GiB: compressed, GDAL cannot tell ahead


def local_crs(origin: LocalFrame) -> str:
    """PROJ string of the projection whose (x, y) are the local ENU frame's (east, north) metres: a transverse
    Mercator centred at the origin, on WGS84. Its scale k_0 = 1 + h / sqrt(M N) carries the origin's ellipsoidal
    height h (M, N: the radii of curvature there): the ENU frame measures at the origin's height, the projection
    on the ellipsoid (without it, 8 cm per km at 520 m). Ground points at the origin's height land within 0.2 cm
    of their ENU position 5 km out, 7 cm 20 km out (tests/mapping/test_map_files.py)."""
    s2 = np.sin(np.radians(origin.lat_deg)) ** 2
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s2)
    m = WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s2) ** 1.5
    k0 = 1.0 + origin.alt_m / float(np.sqrt(m * n))
    return (f"+proj=tmerc +lat_0={origin.lat_deg:.10f} +lon_0={origin.lon_deg:.10f} +k_0={k0:.12f} "
            f"+x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs")


def north_up_transform(origin_xy: tuple[float, float], resolution_m: float, rows: int) -> Affine:
    """The GeoTIFF's pixel -> (x, y) of a raster whose cell (i, j) is centred at origin + (j, i) * res, written
    north up (its row i lands at row rows - 1 - i)."""
    x0, y0 = origin_xy
    return Affine(resolution_m, 0.0, x0 - resolution_m / 2, 0.0, -resolution_m, y0 + (rows - 0.5) * resolution_m)


def _open(path: Path, array: np.ndarray, bands: int, grid: tuple[tuple[float, float], float], crs: str | None,
          **profile):
    return rasterio.open(path, "w", **_PROFILE, width=array.shape[1], height=array.shape[0], count=bands,
                         dtype=array.dtype, crs=crs, transform=north_up_transform(*grid, array.shape[0]), **profile)


def _write_north_up(dst, array: np.ndarray) -> None:
    """`array` (rows south to north, (H, W) or (H, W, B)) into `dst`, north up, ROWS_PER_WRITE rows at a time."""
    h = array.shape[0]
    for r0 in range(0, h, ROWS_PER_WRITE):
        r1 = min(h, r0 + ROWS_PER_WRITE)
        block = np.flipud(np.asarray(array[r0:r1]))
        window = rasterio.windows.Window(0, h - r1, array.shape[1], r1 - r0)
        dst.write(block[None] if block.ndim == 2 else np.moveaxis(block, 2, 0), window=window)


def write_elevation(path: Path, elevation: np.ndarray, grid: tuple[tuple[float, float], float],
                    crs: str | None) -> Path:
    with _open(path, elevation, 1, grid, crs, nodata=np.nan) as dst:
        dst.units = ("metre",)
        dst.descriptions = ("height above the local ENU frame's origin (its z), m",)
        _write_north_up(dst, elevation)
    return path


def write_semantics(path: Path, labels: np.ndarray, grid: tuple[tuple[float, float], float],
                    crs: str | None) -> Path:
    with _open(path, labels, 1, grid, crs, nodata=NO_LABEL, photometric="palette") as dst:
        colours = {c: (0, 0, 0, 0) for c in range(256)}
        colours.update({int(c): (*map(int, CLASS_COLOURS[c]), 255) for c in SemanticClass})
        dst.write_colormap(1, colours)
        dst.descriptions = ("semantic class id",)
        dst.update_tags(1, classes=", ".join(f"{int(c)}={c.name.lower()}" for c in SemanticClass),
                        no_label=str(NO_LABEL))
        _write_north_up(dst, labels)
    return path


def write_rgb(path: Path, rgb: np.ndarray, mapped: np.ndarray, grid: tuple[tuple[float, float], float],
              crs: str | None) -> Path:
    """An (H, W, 3) uint8 raster with `mapped` (H, W) as its mask (unmapped cells transparent, not black)."""
    with _open(path, rgb, 3, grid, crs, photometric="rgb") as dst:
        _write_north_up(dst, rgb)
        dst.write_mask(np.flipud(mapped).astype(np.uint8) * 255)
    return path
