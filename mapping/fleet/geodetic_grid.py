"""The fleet's shared map grid on the earth: square tiles of TILE_M metres in the UTM zone of their place (WGS84),
cells of the map's resolution, each tile named by a global id (`32N_17167_133271`: zone, hemisphere, tile column
and row of easting / northing), so that drives with different local ENU origins, on different days, land in the
same tiles and cells. Heights are ellipsoidal (WGS84) metres.

A tile's cells are placed in a drive's local ENU frame exactly on a coarse lattice (every LATTICE_CELLS cells:
UTM -> WGS84 -> ENU) and bilinearly between (the projection is smooth far below a millimetre over that span)."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from rasterio.crs import CRS
from rasterio.warp import transform

from daemon.spine.local_frame import LocalFrame

TILE_M = 40.0  # a tile's side, m
LATTICE_CELLS = 16  # the exact transform every this many cells, bilinear between
_TILE_ID = re.compile(r"^(\d{1,2})([NS])_(-?\d+)_(-?\d+)$")
_WGS84 = CRS.from_epsg(4326)


@dataclass(frozen=True, order=True)
class TileId:
    """One tile of the grid: UTM zone and hemisphere, column (easting // TILE_M), row (northing // TILE_M)."""

    zone: int
    south: bool
    col: int
    row: int

    def __str__(self) -> str:
        return f"{self.zone}{'S' if self.south else 'N'}_{self.col}_{self.row}"

    @staticmethod
    def parse(text: str) -> TileId:
        m = _TILE_ID.match(text)
        if m is None:
            raise ValueError(f"{text!r} is not a tile id (ZONE[NS]_COL_ROW)")
        return TileId(int(m[1]), m[2] == "S", int(m[3]), int(m[4]))

    @property
    def crs(self) -> CRS:
        return utm_crs(self.zone, self.south)


def utm_crs(zone: int, south: bool) -> CRS:
    return CRS.from_epsg((32700 if south else 32600) + zone)


def utm_zone(lat_deg: float, lon_deg: float) -> tuple[int, bool]:
    """The standard UTM zone of a place (without the Norway / Svalbard exceptions: one rule for every drive)."""
    return int(np.floor((lon_deg + 180.0) / 6.0)) % 60 + 1, lat_deg < 0


@dataclass(frozen=True)
class GridSpec:
    """The grid's cell size; a tile holds `cells` x `cells` of them."""

    resolution_m: float

    @property
    def cells(self) -> int:
        return int(round(TILE_M / self.resolution_m))

    def cell_centres(self, tile: TileId, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """UTM (easting, northing) of cells (rows, cols) of `tile`: row r, column c centred at
        (col * TILE_M + (c + 0.5) * res, row * TILE_M + (r + 0.5) * res)."""
        res = self.resolution_m
        return tile.col * TILE_M + (cols + 0.5) * res, tile.row * TILE_M + (rows + 0.5) * res


def enu_to_utm(frame: LocalFrame, enu: np.ndarray, zone: int, south: bool) -> np.ndarray:
    """(N, 3) local ENU points -> (N, 3) UTM easting, northing and ellipsoidal height."""
    lat, lon, h = frame.enu_to_geodetic(np.asarray(enu, np.float64))
    e, n = transform(_WGS84, utm_crs(zone, south), np.atleast_1d(lon).tolist(), np.atleast_1d(lat).tolist())
    return np.stack([np.asarray(e), np.asarray(n), np.atleast_1d(h)], 1)


def utm_to_enu_xy(frame: LocalFrame, easting: np.ndarray, northing: np.ndarray, zone: int, south: bool,
                  height_m: float) -> np.ndarray:
    """UTM points at ellipsoidal height `height_m` -> (N, 2) local ENU (x, y)."""
    lon, lat = transform(utm_crs(zone, south), _WGS84, np.ravel(easting).tolist(), np.ravel(northing).tolist())
    enu = frame.geodetic_to_enu(np.asarray(lat), np.asarray(lon), np.full(len(lat), height_m))
    return np.asarray(enu)[:, :2]


def tile_in_frame(frame: LocalFrame, tile: TileId, grid: GridSpec, height_m: float) -> np.ndarray:
    """(cells, cells, 2) local ENU (x, y) of every cell centre of `tile`: exact on the lattice, bilinear between."""
    n = grid.cells
    knots = np.unique(np.concatenate([np.arange(0, n, LATTICE_CELLS), [n - 1]]))
    kr, kc = np.meshgrid(knots, knots, indexing="ij")
    e, nn = grid.cell_centres(tile, kr.ravel().astype(np.float64), kc.ravel().astype(np.float64))
    xy = utm_to_enu_xy(frame, e, nn, tile.zone, tile.south, height_m).reshape(len(knots), len(knots), 2)
    # bilinear between the knots, rows then columns
    fine = np.empty((n, n, 2), np.float64)
    at = np.arange(n, dtype=np.float64)
    seg = np.clip(np.searchsorted(knots, at, side="right") - 1, 0, len(knots) - 2)
    frac = (at - knots[seg]) / (knots[seg + 1] - knots[seg])
    for k in range(2):
        rows = xy[seg, :, k] * (1 - frac)[:, None] + xy[seg + 1, :, k] * frac[:, None]  # (n, knots)
        fine[:, :, k] = rows[:, seg] * (1 - frac)[None, :] + rows[:, seg + 1] * frac[None, :]
    return fine


def tiles_under(frame: LocalFrame, xy: np.ndarray, height_m: float) -> list[TileId]:
    """The tiles the local ENU points (N, 2) at ellipsoidal height `height_m` fall in, each in its own UTM zone."""
    lat, lon, _ = frame.enu_to_geodetic(np.column_stack([xy, np.full(len(xy), height_m - frame.alt_m)]))
    zones = [utm_zone(a, o) for a, o in zip(np.atleast_1d(lat), np.atleast_1d(lon), strict=True)]
    tiles: set[TileId] = set()
    for zone, south in set(zones):
        mine = np.array([z == (zone, south) for z in zones])
        e, n = transform(_WGS84, utm_crs(zone, south), np.atleast_1d(lon)[mine].tolist(),
                         np.atleast_1d(lat)[mine].tolist())
        cols = np.floor(np.asarray(e) / TILE_M).astype(np.int64).tolist()
        rows = np.floor(np.asarray(n) / TILE_M).astype(np.int64).tolist()
        tiles.update(TileId(zone, south, c, r) for c, r in set(zip(cols, rows, strict=True)))
    return sorted(tiles)
