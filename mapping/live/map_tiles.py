"""The live map on disk: square tiles of BEV rasters on one global grid, and the mosaic of them all.

The grid is aligned to multiples of the resolution: cell (i, j) of the whole map is centred at
(j * res, i * res) in the drive's local ENU frame. A tile of `tile_cells` x `tile_cells` cells is one
file `tile_<ti>_<tj>.npz` holding elevation (float32, NaN = unmapped), semantic labels (uint8), RGB per
camera and `owner`: the window that wrote each cell, negative (-1 - window) when the cell lay outside
that window's central stretch. A window's cells overwrite what is there when they lie in its central
stretch, or when the cell holds nothing yet or only another window's margin. Tiles are read, merged
and written back per window, never cached: memory does not grow with the drive.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapping.method.road_map import NO_LABEL

NO_OWNER = np.iinfo(np.int32).min


@dataclass(frozen=True)
class WindowRaster:
    """One window's BEV on the global grid: cell (r, c) is global cell (i0 + r, j0 + c)."""

    i0: int
    j0: int
    elevation: np.ndarray  # (H, W) float32, NaN where not observed
    labels: np.ndarray  # (H, W) uint8
    rgb: dict[str, np.ndarray]  # camera -> (H, W, 3) uint8
    central: np.ndarray  # (H, W) bool: inside the window's central stretch


def tile_path(folder: Path, ti: int, tj: int) -> Path:
    return folder / f"tile_{ti}_{tj}.npz"


def _empty_tile(n: int, cameras: list[str]) -> dict[str, np.ndarray]:
    tile = {"elevation": np.full((n, n), np.nan, np.float32), "labels": np.full((n, n), NO_LABEL, np.uint8),
            "owner": np.full((n, n), NO_OWNER, np.int32)}
    for c in cameras:
        tile[f"rgb_{c}"] = np.zeros((n, n, 3), np.uint8)
    return tile


def load_tile(path: Path, n: int, cameras: list[str]) -> dict[str, np.ndarray]:
    if not path.exists():
        return _empty_tile(n, cameras)
    with np.load(path) as z:
        tile = {k: z[k] for k in z.files}
    for key, value in _empty_tile(n, cameras).items():
        tile.setdefault(key, value)
    return tile


def save_atomically(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def write_window(folder: Path, tile_cells: int, window: int, raster: WindowRaster, cameras: list[str]) -> list[str]:
    """Merge a window's raster into the tiles it touches; returns the tile file names written."""
    folder.mkdir(parents=True, exist_ok=True)
    h, w = raster.elevation.shape
    observed = np.isfinite(raster.elevation)
    written = []
    n = tile_cells
    for ti in range(raster.i0 // n, (raster.i0 + h - 1) // n + 1):
        for tj in range(raster.j0 // n, (raster.j0 + w - 1) // n + 1):
            # the part of the window raster inside this tile
            r0, r1 = max(ti * n, raster.i0), min((ti + 1) * n, raster.i0 + h)
            c0, c1 = max(tj * n, raster.j0), min((tj + 1) * n, raster.j0 + w)
            src = (slice(r0 - raster.i0, r1 - raster.i0), slice(c0 - raster.j0, c1 - raster.j0))
            if not observed[src].any():
                continue
            dst = (slice(r0 - ti * n, r1 - ti * n), slice(c0 - tj * n, c1 - tj * n))
            path = tile_path(folder, ti, tj)
            tile = load_tile(path, n, cameras)
            old_owner = tile["owner"][dst]
            central = raster.central[src]
            take = observed[src] & (central | (old_owner < 0))
            tile["owner"][dst] = np.where(take, np.where(central, window, -1 - window), old_owner)
            tile["elevation"][dst] = np.where(take, raster.elevation[src], tile["elevation"][dst])
            tile["labels"][dst] = np.where(take, raster.labels[src], tile["labels"][dst])
            for c in cameras:
                tile[f"rgb_{c}"][dst] = np.where(take[..., None], raster.rgb[c][src], tile[f"rgb_{c}"][dst])
            save_atomically(path, tile)
            written.append(path.name)
    return written


def tile_indices(folder: Path) -> list[tuple[int, int]]:
    out = []
    for path in folder.glob("tile_*_*.npz"):
        parts = path.stem.split("_")
        out.append((int(parts[1]), int(parts[2])))
    return sorted(out)


@dataclass(frozen=True)
class Mosaic:
    """The whole map at `stride` x the grid resolution: cell (i, j) centred at origin + (j, i) * resolution."""

    origin_xy: tuple[float, float]
    resolution_m: float
    elevation: np.ndarray
    labels: np.ndarray
    rgb: dict[str, np.ndarray]
    owner: np.ndarray


def _tiles_in(folder: Path) -> list[tuple[int, int]]:
    """The (ti, tj) tiles written in `folder`; an error if there are none."""
    tiles = tile_indices(folder)
    if not tiles:
        raise ValueError(f"no map tiles in {folder}")
    return tiles


def _layout(tiles: list[tuple[int, int]], tile_cells: int, max_cells: int) -> tuple[int, int, int, int, int]:
    """(ti0, ti1, tj0, tj1, stride): the tiles' bounding box and the integer stride keeping it under max_cells."""
    n = tile_cells
    ti0, ti1 = min(t[0] for t in tiles), max(t[0] for t in tiles)
    tj0, tj1 = min(t[1] for t in tiles), max(t[1] for t in tiles)
    full_h, full_w = (ti1 - ti0 + 1) * n, (tj1 - tj0 + 1) * n
    stride = 1
    while (full_h // stride) * (full_w // stride) > max_cells or n % stride:
        stride += 1
    return ti0, ti1, tj0, tj1, stride


def mosaic(folder: Path, tile_cells: int, grid_m: float, cameras: list[str], max_cells: int = 40_000_000) -> Mosaic:
    """All tiles in one raster; subsampled by an integer stride when the full one would exceed max_cells."""
    tiles = _tiles_in(folder)
    n = tile_cells
    ti0, ti1, tj0, tj1, stride = _layout(tiles, n, max_cells)
    m = n // stride
    h, w = (ti1 - ti0 + 1) * m, (tj1 - tj0 + 1) * m
    out = _empty_tile(1, cameras)
    out = {k: np.broadcast_to(v[:1, :1], (h, w) + v.shape[2:]).copy() for k, v in out.items()}
    for ti, tj in tiles:
        tile = load_tile(tile_path(folder, ti, tj), n, cameras)
        rows = slice((ti - ti0) * m, (ti - ti0 + 1) * m)
        cols = slice((tj - tj0) * m, (tj - tj0 + 1) * m)
        for k in out:
            out[k][rows, cols] = tile[k][::stride, ::stride]
    res = grid_m * stride
    return Mosaic((tj0 * n * grid_m, ti0 * n * grid_m), res, out["elevation"], out["labels"],
                  {c: out[f"rgb_{c}"] for c in cameras}, out["owner"])


@dataclass(frozen=True)
class RasterGrid:
    """Where the cells of a written raster lie: cell (i, j) centred at origin + (j, i) * resolution."""

    origin_xy: tuple[float, float]
    resolution_m: float
    shape: tuple[int, int]


def write_mosaic_npy(folder: Path, tile_cells: int, grid_m: float, paths: dict[str, Path],
                     max_cells: int = 40_000_000) -> RasterGrid:
    """The mosaic's `elevation` and/or `labels` as .npy files (key -> path), written one row of tiles at a
    time: memory holds one row of tiles, never the map's bounding box (mostly empty on a long drive)."""
    tiles = _tiles_in(folder)
    n = tile_cells
    ti0, ti1, tj0, tj1, stride = _layout(tiles, n, max_cells)
    m = n // stride
    shape = ((ti1 - ti0 + 1) * m, (tj1 - tj0 + 1) * m)
    empty = _empty_tile(1, [])
    rows: dict[int, list[int]] = {}
    for ti, tj in tiles:
        rows.setdefault(ti, []).append(tj)
    files = {k: open(path.with_name(path.name + ".tmp"), "wb") for k, path in paths.items()}
    try:
        for k, f in files.items():
            np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(empty[k].dtype),
                                                     "fortran_order": False, "shape": shape})
        for ti in range(ti0, ti1 + 1):
            strips = {k: np.full((m, shape[1]), empty[k][0, 0], empty[k].dtype) for k in files}
            for tj in rows.get(ti, []):
                tile = load_tile(tile_path(folder, ti, tj), n, [])
                for k, strip in strips.items():
                    strip[:, (tj - tj0) * m:(tj - tj0 + 1) * m] = tile[k][::stride, ::stride]
            for k, f in files.items():
                f.write(strips[k].tobytes())
    finally:
        for f in files.values():
            f.close()
    for path in paths.values():
        os.replace(path.with_name(path.name + ".tmp"), path)
    return RasterGrid((tj0 * n * grid_m, ti0 * n * grid_m), grid_m * stride, shape)


@dataclass(frozen=True)
class MappedCells:
    """Mapped cells on a grid subsampled by a stride: cell (i, j) centred at (j, i) * resolution_m, sorted by (i, j)."""

    i: np.ndarray
    j: np.ndarray
    elevation: np.ndarray  # float32
    rgb: np.ndarray  # (N, 3) uint8, of one camera
    resolution_m: float


def mapped_cells(folder: Path, tile_cells: int, grid_m: float, camera: str, max_cells: int) -> MappedCells:
    """Every mapped cell of the tiles, at the smallest stride (a divisor of tile_cells) that keeps them under
    max_cells: memory in proportion to the road mapped, never to the map's bounding box."""
    tiles = _tiles_in(folder)
    n = tile_cells
    strides = [s for s in range(1, n + 1) if n % s == 0]
    counts = np.zeros(len(strides), np.int64)
    for ti, tj in tiles:
        finite = np.isfinite(load_tile(tile_path(folder, ti, tj), n, [])["elevation"])
        counts += [int(finite[::s, ::s].sum()) for s in strides]
    stride = next((s for s, c in zip(strides, counts, strict=True) if c <= max_cells), strides[-1])
    m = n // stride
    parts = []
    for ti, tj in tiles:
        tile = load_tile(tile_path(folder, ti, tj), n, [camera])
        z = tile["elevation"][::stride, ::stride]
        r, c = np.nonzero(np.isfinite(z))
        parts.append((ti * m + r, tj * m + c, z[r, c], tile[f"rgb_{camera}"][::stride, ::stride][r, c]))
    i, j, z, rgb = (np.concatenate([p[k] for p in parts]) for k in range(4))
    order = np.lexsort((j, i))
    return MappedCells(i[order].astype(np.int64), j[order].astype(np.int64), z[order], rgb[order], grid_m * stride)
