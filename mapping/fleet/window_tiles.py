"""One window's road map cut into the shared grid's tiles: its bird's-eye rasters in the drive's local ENU frame
(map_export.bev_rasters, with their confidences) sampled at every tile cell's place in that frame (nearest cell:
both grids have the map's resolution), heights turned into ellipsoidal ones."""

from __future__ import annotations

import numpy as np

from daemon.spine.local_frame import LocalFrame
from mapping.fleet.geodetic_grid import GridSpec, TileId, tile_in_frame, tiles_under
from mapping.fleet.tile_store import Contribution
from mapping.method.road_map import RoadMap
from mapping.outputs.map_export import bev_rasters

_FOOTPRINT_STRIDE = 5  # the tiles a window touches are found from every 5th mapped cell (and its neighbours)


def window_contributions(road_map: RoadMap, frame: LocalFrame, drive: str, window: int, cameras: list[str],
                         grid: GridSpec, threads: int = 1) -> dict[TileId, Contribution]:
    """What the window's map gives each tile it reaches (tiles it maps no cell of are left out)."""
    res = grid.resolution_m
    bev = bev_rasters(road_map, cameras, res, threads, confidence=True)
    z = bev["elevation"]
    mapped = np.isfinite(z)
    if not mapped.any():
        return {}
    x0, y0 = bev["origin_xy"]
    ii, jj = np.nonzero(mapped)
    pick = slice(None, None, _FOOTPRINT_STRIDE)
    xy = np.column_stack([x0 + jj[pick] * res, y0 + ii[pick] * res])
    ring = np.array([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]]) * _FOOTPRINT_STRIDE * res
    mean_height = frame.alt_m + float(np.nanmedian(z))
    tiles = tiles_under(frame, (xy[:, None, :] + ring[None]).reshape(-1, 2), mean_height)
    out = {}
    for tile in tiles:
        cell_xy = tile_in_frame(frame, tile, grid, mean_height)
        j = np.rint((cell_xy[..., 0] - x0) / res).astype(np.int64)
        i = np.rint((cell_xy[..., 1] - y0) / res).astype(np.int64)
        inside = (i >= 0) & (i < z.shape[0]) & (j >= 0) & (j < z.shape[1])
        src = (np.where(inside, i, 0), np.where(inside, j, 0))
        take = inside & mapped[src]
        if not take.any():
            continue
        n = grid.cells
        height = np.full((n, n), np.nan, np.float32)
        enu = np.column_stack([cell_xy[take], z[src][take]])
        height[take] = frame.enu_to_geodetic(enu)[2]  # ellipsoidal: the earth's curvature taken out
        weight = np.where(take, bev["weight"][src], 0.0).astype(np.float32)
        prob = bev["class_prob"]
        class_prob = (np.where(take[..., None], np.rint(prob[src] * 255), 0).astype(np.uint8)
                      if prob is not None else None)
        rgb = {c: np.where(take[..., None], bev["rgb"][c][src], 0).astype(np.uint8) for c in cameras}
        out[tile] = Contribution(drive, window, height, weight, class_prob, rgb)
    return out
