"""The fleet's tile store (mapping/fleet): global tile ids on a UTM grid that two drives with different local ENU
origins share cell for cell; a window's map cut into tile contributions that keep its heights (ellipsoidal), its
confidences and colours; the files written atomically, read back whole, and a window written twice stored once."""

from __future__ import annotations

import numpy as np
import pytest

from daemon.spine.local_frame import LocalFrame
from mapping.fits.reconstruction import reconstruct
from mapping.fleet.geodetic_grid import TILE_M, GridSpec, TileId, enu_to_utm, tile_in_frame, tiles_under, utm_zone
from mapping.fleet.tile_store import TileStore
from mapping.fleet.window_tiles import window_contributions
from mapping.outputs.map_export import bev_rasters
from tests.mapping.synthetic_road_scene import make_scene
from tests.mapping.test_mapping_reconstruction import CONFIG

ORIGIN = LocalFrame(48.137, 11.575, 520.0)
GRID = GridSpec(0.1)


def test_tile_ids_are_global_and_read_back():
    tile = TileId(32, False, 17167, 133271)
    assert TileId.parse(str(tile)) == tile and str(tile) == "32N_17167_133271"
    assert TileId.parse("19S_-3_40") == TileId(19, True, -3, 40)
    with pytest.raises(ValueError):
        TileId.parse("tile_3_4")
    assert utm_zone(48.1, 11.5) == (32, False) and utm_zone(-33.9, 151.2) == (56, True)


def test_two_local_frames_put_one_place_in_the_same_tile_cell():
    # a second drive's ENU origin 700 m east, 400 m north and 30 m higher than the first's
    other = LocalFrame(*(float(v) for v in ORIGIN.enu_to_geodetic(np.array([700.0, 400.0, 30.0]))))
    place_first = np.array([[712.34, 398.76, -2.0]])  # one point of the road in the first frame
    place_other = other.geodetic_to_enu(*ORIGIN.enu_to_geodetic(place_first[0]))[None]
    a, b = enu_to_utm(ORIGIN, place_first, 32, False), enu_to_utm(other, place_other, 32, False)
    assert np.allclose(a, b, atol=1e-4)  # easting, northing and ellipsoidal height
    (tile,) = tiles_under(ORIGIN, place_first[:, :2], 518.0)
    assert tiles_under(other, place_other[:, :2], 518.0) == [tile]
    # every cell of that tile lies at the same place seen from both frames: the bilinear lattice is exact to < 1 mm
    xy_first, xy_other = tile_in_frame(ORIGIN, tile, GRID, 518.0), tile_in_frame(other, tile, GRID, 518.0)
    back = other.geodetic_to_enu(*ORIGIN.enu_to_geodetic(np.column_stack([xy_first.reshape(-1, 2),
                                                                          np.full(GRID.cells ** 2, -2.0)])))
    assert np.abs(back[:, :2] - xy_other.reshape(-1, 2)).max() < 0.02  # the height guessed, 2 m off: < 2 cm
    r, c = np.unravel_index(np.argmin(np.linalg.norm(xy_first - place_first[0, :2], axis=2)), xy_first.shape[:2])
    assert np.linalg.norm(xy_first[r, c] - place_first[0, :2]) <= GRID.resolution_m * 0.71  # the place's own cell
    e, n = GRID.cell_centres(tile, np.array([r]), np.array([c]))
    assert abs(e[0] - a[0, 0]) <= 0.05 + 1e-6 and abs(n[0] - a[0, 1]) <= 0.05 + 1e-6
    assert tile.col == int(a[0, 0] // TILE_M) and tile.row == int(a[0, 1] // TILE_M)


@pytest.fixture(scope="module")
def window_map():
    scene = make_scene(length_m=12.0, width=64, height=36, rate_hz=10.0)
    result = reconstruct(scene.keyframes, scene.cameras, scene.trajectory, scene.lidar, CONFIG,
                         scene.reference_height_m, None, holdout_every=0, progress=False)
    return result.road_map, sorted(scene.cameras)


def test_a_windows_map_lands_in_its_tiles_with_its_heights_and_confidences(window_map, tmp_path):
    road_map, cameras = window_map
    parts = window_contributions(road_map, ORIGIN, "drive0", 3, cameras, GRID)
    assert parts
    bev = bev_rasters(road_map, cameras, GRID.resolution_m, 1, confidence=True)
    mapped = np.isfinite(bev["elevation"]).sum()
    cells = sum(int(np.isfinite(p.height).sum()) for p in parts.values())
    assert abs(cells - mapped) < 0.05 * mapped  # resampled, not lost (the grids are turned by < 1 degree)
    store = TileStore(tmp_path)
    for tile, part in parts.items():
        store.write(tile, part)
    for tile, part in parts.items():  # the same window again: replaced, not added
        store.write(tile, part)
    assert store.tiles() == sorted(parts)
    assert not list(tmp_path.rglob("*.tmp"))
    heights = []
    for tile in store.tiles():
        (info,) = store.contributions(tile)
        assert (info.drive, info.window, info.cameras) == ("drive0", 3, cameras)
        back = store.read(tile, info)
        assert np.array_equal(back.height, parts[tile].height, equal_nan=True)
        assert info.cells == int(np.isfinite(back.height).sum())
        seen = np.isfinite(back.height)
        assert (back.weight[seen] > 0).all() and (back.weight[~seen] == 0).all()
        assert back.class_prob is not None and np.abs(back.class_prob[seen].sum(-1).astype(int) - 255).max() <= 3
        assert all(back.rgb[c][seen].any() for c in cameras)
        heights.append(back.height[seen])
    # the map's local heights, as ellipsoidal ones: ORIGIN's 520 m plus z (a 12 m road: curvature < 1 cm)
    z = bev["elevation"][np.isfinite(bev["elevation"])]
    assert np.median(np.concatenate(heights)) == pytest.approx(520.0 + np.median(z), abs=0.02)
