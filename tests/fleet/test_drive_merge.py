"""Two drives of one road merged (mapping.fleet.drive_merge) from real tile-store files: the second drive's map
shifted by a few cells, 5 cm higher and with another colour response, each with a hole (a parked car) where the
other saw the road. The merge finds the shift and the height offset from the overlap, puts both in their
consensus frame, maps the second drive's colours onto the first's and fills each hole from the other drive."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from daemon.spine.semantic_classes import CLASS_COLOURS, NUM_MAP_CLASSES, SemanticClass
from mapping.fleet.drive_merge import drive_layers, fuse, merge_drives, shifted
from mapping.fleet.fleet_journal import FleetJournal
from mapping.fleet.geodetic_grid import GridSpec, TileId
from mapping.fleet.tile_store import Contribution, TileStore

GRID = GridSpec(0.1)
TILE = TileId(32, False, 17291, 133368)
N = GRID.cells
SHIFT = (2, -3)  # drive b's map moved by (rows north, columns east)


def _road() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Classes, heights and colours of a road across the tile: curbs, a dashed centre line, a stop line."""
    rows, cols = np.mgrid[0:N, 0:N]
    cls = np.full((N, N), int(SemanticClass.BACKGROUND))
    cls[(rows >= 60) & (rows < 340)] = SemanticClass.ROAD
    cls[((rows >= 55) & (rows < 60)) | ((rows >= 340) & (rows < 345))] = SemanticClass.CURB
    cls[(rows >= 197) & (rows < 202) & ((cols // 45) % 2 == 0)] = SemanticClass.LANE_MARKING
    cls[(rows >= 60) & (rows < 197) & (cols >= 230) & (cols < 235)] = SemanticClass.LANE_MARKING
    height = (520.0 + 0.002 * cols + np.where(cls == SemanticClass.CURB, 0.15, 0.0)).astype(np.float32)
    texture = np.random.default_rng(1).normal(0, 6, (N, N, 3))
    rgb = np.clip(CLASS_COLOURS[cls] * 0.5 + 40 + texture, 0, 255)
    return cls, height, rgb


def _contribution(drive: str, cls, height, rgb, hole, mapped) -> Contribution:
    seen = mapped & ~hole
    prob = np.zeros((N, N, NUM_MAP_CLASSES), np.uint8)
    prob[seen, np.minimum(cls[seen], NUM_MAP_CLASSES - 1)] = 255
    return Contribution(drive, 0, np.where(seen, height, np.nan).astype(np.float32),
                        np.where(seen, 2.0, 0.0).astype(np.float32), prob,
                        {"cam": np.where(seen[..., None], rgb, 0).astype(np.uint8)})


@pytest.fixture
def store(tmp_path):
    cls, height, rgb = _road()
    rows, cols = np.mgrid[0:N, 0:N]
    mapped = (rows >= 40) & (rows < 360) & (cols >= 20) & (cols < 380)
    hole_a = (rows >= 70) & (rows < 130) & (cols >= 100) & (cols < 160)
    hole_b = (rows >= 240) & (rows < 300) & (cols >= 260) & (cols < 320)
    store = TileStore(tmp_path)
    store.write(TILE, _contribution("a", cls, height, rgb, hole_a, mapped))
    di, dj = SHIFT
    b_rgb = np.clip(rgb * np.array([0.8, 0.9, 1.1]) + 10, 0, 255)  # another exposure and white balance
    b = [shifted(x, di, dj, fill) for x, fill in ((cls, 4), (height + np.float32(0.05), np.nan), (b_rgb, 0))]
    store.write(TILE, _contribution("b", *b, shifted(hole_b, di, dj, False), shifted(mapped, di, dj, False)))
    return store


def test_the_second_drive_is_found_shifted_lifted_and_recoloured(store):
    (mosaic,) = drive_layers(store)
    merged = fuse(mosaic)
    report = {r["drive"]: r for r in merged.alignment}
    assert report["a"]["reference"] != report["b"]["reference"]
    east = report["b"]["shift_m"][0] - report["a"]["shift_m"][0]
    north = report["b"]["shift_m"][1] - report["a"]["shift_m"][1]
    # b is moved back onto a: by -SHIFT
    assert (round(north / 0.1), round(east / 0.1)) == (-SHIFT[0], -SHIFT[1])
    assert report["b"]["dz_m"] - report["a"]["dz_m"] == pytest.approx(-0.05, abs=0.005)
    colour = report["b"]["colour"]["cam"] if "colour" in report["b"] else report["a"]["colour"]["cam"]
    assert colour["rms_after"] < 0.5 * colour["rms_before"]


def test_each_hole_is_filled_by_the_other_drive(store, tmp_path):
    (mosaic,) = drive_layers(store)
    a, b = mosaic.layers["a"], mosaic.layers["b"]
    merged = fuse(mosaic)
    mapped = np.isfinite(merged.height)
    assert mapped.sum() > max(a.mapped.sum(), b.mapped.sum())
    assert mapped[70:130, 100:160].all() and mapped[245:295, 265:315].all()  # both parked cars' holes
    # the merged labels are the road's (where both agree after alignment the classes are crisp)
    cls, _, _ = _road()
    inner = (slice(80, 320), slice(40, 360))
    assert (merged.labels[inner] == cls[inner]).mean() > 0.97  # within a cell of the consensus frame
    report = merge_drives(store, tmp_path / "map")
    (zone,) = report["zones"]
    assert zone["drives"] == ["a", "b"] and zone["crs"] == "EPSG:32632"
    assert json.loads((tmp_path / "map" / "metadata.json").read_text())["zones"][0]["tiles"] == [str(TILE)]
    with rasterio.open(tmp_path / "map" / "bev_elevation.tif") as tif:
        assert tif.crs.to_epsg() == 32632
        assert tif.bounds.left == pytest.approx(TILE.col * 40.0) and tif.bounds.bottom == pytest.approx(TILE.row * 40.0)
    with np.load(store.merged_path(TILE)) as z:
        assert np.array_equal(z["labels"], merged.labels)


def _soft_road(d_north_m: float, d_east_m: float, dashes: bool) -> np.ndarray:
    """Class probabilities (N, N, classes) of an east-west road moved by (north, east) metres, each cell the share
    of its 4 x 4 sub-samples in each class: curbs, a centre line (dashed with a manhole and a stop line, or one
    unbroken line, which fixes nothing along the road)."""
    sub = 4
    fine = (np.arange(N * sub) + 0.5) / sub * GRID.resolution_m
    y = fine[:, None] - d_north_m  # the world point each sub-sample sees
    x = fine[None, :] - d_east_m
    cls = np.full(y.shape[:1] + x.shape[1:], int(SemanticClass.BACKGROUND))
    cls[((y >= 6.0) & (y < 34.0)) * np.ones_like(x, bool)] = SemanticClass.ROAD
    curb = ((y >= 5.5) & (y < 6.0)) | ((y >= 34.0) & (y < 34.5))
    cls[curb * np.ones_like(x, bool)] = SemanticClass.CURB
    line = (y >= 19.9) & (y < 20.1)
    if dashes:
        cls[line & ((x % 9.0) < 3.0)] = SemanticClass.LANE_MARKING
        cls[(y >= 6.0) & (y < 19.9) & (x >= 23.0) & (x < 23.5)] = SemanticClass.LANE_MARKING  # a stop line
        cls[(np.abs(y - 12.0) < 0.3) & (np.abs(x - 30.0) < 0.3)] = SemanticClass.MANHOLE
    else:
        cls[line * np.ones_like(x, bool)] = SemanticClass.LANE_MARKING
    one_hot = np.eye(NUM_MAP_CLASSES, dtype=np.float32)[cls]
    return one_hot.reshape(N, sub, N, sub, NUM_MAP_CLASSES).mean((1, 3))


def _soft_store(tmp_path, d_north_m: float, d_east_m: float, dashes: bool) -> TileStore:
    store = TileStore(tmp_path / ("dashed" if dashes else "unbroken"))
    rows, cols = np.mgrid[0:N, 0:N]
    mapped = (rows >= 40) & (rows < 360) & (cols >= 20) & (cols < 380)
    for drive, (dn, de) in (("a", (0.0, 0.0)), ("b", (d_north_m, d_east_m))):
        prob = _soft_road(dn, de, dashes)
        store.write(TILE, Contribution(drive, 0, np.where(mapped, 520.0, np.nan).astype(np.float32),
                                       np.where(mapped, 2.0, 0.0).astype(np.float32),
                                       np.where(mapped[..., None], prob * 255 + 0.5, 0).astype(np.uint8), {}))
    return store


def _relative_shift_m(merged) -> np.ndarray:
    report = {r["drive"]: r for r in merged.alignment}
    return np.array(report["b"]["shift_m"]) - np.array(report["a"]["shift_m"])  # (east, north) moving b onto a


def test_a_shift_below_a_cell_is_found_along_the_road_from_dashes_a_stop_line_and_a_manhole(tmp_path):
    # b's map lies 0.27 m east (along the road) and 0.04 m north of a's: neither a whole number of 0.1 m cells
    (mosaic,) = drive_layers(_soft_store(tmp_path, 0.04, 0.27, dashes=True))
    merged = fuse(mosaic)
    assert _relative_shift_m(merged) == pytest.approx([-0.27, -0.04], abs=0.02)


def test_along_an_unbroken_line_nothing_fixes_the_along_road_shift_and_the_merge_says_so(tmp_path):
    (mosaic,) = drive_layers(_soft_store(tmp_path, 0.04, 0.27, dashes=False))
    merged = fuse(mosaic)
    east, north = _relative_shift_m(merged)
    assert north == pytest.approx(-0.04, abs=0.02)  # across the road: the curbs and the line fix it
    assert abs(east) < 0.1  # along it the prior keeps the drives' GNSS (no shift), not a guess from noise
    report = next(r for r in merged.alignment if not r["reference"])
    weak_east, weak_north = report["least_constrained_direction_en"]
    assert abs(weak_east) > 0.99  # the least constrained direction is along the road
    std_weak, std_strong = report["shift_std_m"]
    assert std_weak > 10 * std_strong


def _plain_store(tmp_path, drives: dict[str, dict]) -> TileStore:
    """A flat road (520 m, ROAD everywhere mapped) per drive, changed where `drives[name]` says: `patch` (rows and
    columns slices) given `height`, `prob` (classes) and `steps` (supervising steps) there, `steps` elsewhere 20;
    `gnss_std_m` into the drive's journal entry."""
    store = TileStore(tmp_path / "plain")
    rows, cols = np.mgrid[0:N, 0:N]
    mapped = (rows >= 40) & (rows < 360) & (cols >= 20) & (cols < 380)
    for drive, spec in drives.items():
        height = np.where(mapped, 520.0 + spec.get("dz", 0.0), np.nan).astype(np.float32)
        prob = np.zeros((N, N, NUM_MAP_CLASSES), np.float32)
        prob[..., int(SemanticClass.ROAD)] = 1.0
        steps = np.full((N, N), 20.0)
        if "patch" in spec:
            at = spec["patch"]
            height[at] += np.float32(spec["height"])
            prob[at] = spec["prob"]
            steps[at] = spec["steps"]
        store.write(TILE, Contribution(drive, 0, height, np.where(mapped, np.log1p(steps), 0).astype(np.float32),
                                       np.where(mapped[..., None], prob * 255 + 0.5, 0).astype(np.uint8), {}))
        FleetJournal(store.root).write_drive(drive, {"windows": 1, "gnss_std_m": spec.get("gnss_std_m")})
    return store


def test_a_cell_seen_often_by_one_drive_and_barely_by_the_other_takes_the_first_ones_height_and_class(tmp_path):
    patch = (slice(150, 250), slice(150, 250))
    mixed = np.zeros(NUM_MAP_CLASSES, np.float32)
    mixed[int(SemanticClass.ROAD)], mixed[int(SemanticClass.LANE_MARKING)] = 0.6, 0.4
    wrong = np.eye(NUM_MAP_CLASSES, dtype=np.float32)[int(SemanticClass.LANE_MARKING)]
    store = _plain_store(tmp_path, {"a": {"patch": patch, "height": 0.0, "prob": mixed, "steps": 100},
                                    "b": {"patch": patch, "height": 0.10, "prob": wrong, "steps": 2}})
    (mosaic,) = drive_layers(store)
    merged = fuse(mosaic)
    # a mean by log(1 + steps) gives b a fifth of the say: +1.9 cm, and the lane marking (2.94 against 2.77)
    assert np.nanmax(np.abs(merged.height[patch] - 520.0)) < 0.005
    assert (merged.labels[patch] == SemanticClass.ROAD).all()
    outside = np.isfinite(merged.height) & ~np.pad(np.ones((100, 100), bool), ((150, 150), (150, 150)))
    assert np.abs(merged.height[outside] - 520.0).max() < 1e-3


@pytest.mark.parametrize("precise", ["a", "b"])
def test_the_map_lies_where_the_drive_with_the_better_reported_gnss_fix_put_it(tmp_path, precise):
    # b's map 0.27 m east, 0.04 m north and 5 cm above a's: one of the two drives reports an RTK fix (1 cm), the
    # other a stand-alone one (1 m); the merge moves the imprecise drive onto the precise one, not both halfway
    store = _soft_store(tmp_path, 0.04, 0.27, dashes=True)
    for drive in ("a", "b"):
        FleetJournal(store.root).write_drive(drive, {"windows": 1,
                                                     "gnss_std_m": [0.01, 0.02] if drive == precise else [1.0, 2.0]})
        if drive == "b":  # b's heights 5 cm up
            info = store.contributions(TILE)[1]
            part = store.read(TILE, info)
            part.height += np.float32(0.05)
            store.write(TILE, part)
    (mosaic,) = drive_layers(store)
    merged = fuse(mosaic)
    report = {r["drive"]: r for r in merged.alignment}
    other = "b" if precise == "a" else "a"
    # the consensus is to whole cells (the class probabilities are not resampled): the precise drive moves by
    # less than half a cell, where halfway would be 0.14 m
    assert np.hypot(*report[precise]["shift_m"]) < GRID.resolution_m / 2 + 0.01
    assert np.subtract(report["b"]["shift_m"], report["a"]["shift_m"]) == pytest.approx([-0.27, -0.04], abs=0.02)
    assert report[precise]["dz_m"] == pytest.approx(0.0, abs=0.002)
    assert report[other]["dz_m"] == pytest.approx(-0.05 if other == "b" else 0.05, abs=0.002)


def test_two_drives_tilted_apart_meet_at_their_mean_tilt_also_where_only_one_of_them_mapped(tmp_path):
    # b's map rises 1 cm per m towards north against a's (another roll error) and sits 3 cm higher; each drive has
    # a hole the other fills. Fused cell by cell alone, the holes would keep the filling drive's own tilt: a step
    # at their edges. Aligned, every cell lies on the mean plane of the two.
    store = TileStore(tmp_path / "tilted")
    rows, cols = np.mgrid[0:N, 0:N]
    mapped = (rows >= 40) & (rows < 360) & (cols >= 20) & (cols < 380)
    holes = {"a": (rows >= 100) & (rows < 160) & (cols >= 100) & (cols < 160),
             "b": (rows >= 260) & (rows < 320) & (cols >= 240) & (cols < 300)}
    north_m = rows * GRID.resolution_m
    tilt = {"a": 0.0, "b": 0.01}
    for drive in ("a", "b"):
        seen = mapped & ~holes[drive]
        height = 520.0 + tilt[drive] * (north_m - 20.0) + (0.03 if drive == "b" else 0.0)
        prob = np.zeros((N, N, NUM_MAP_CLASSES), np.uint8)
        prob[seen, int(SemanticClass.ROAD)] = 255
        store.write(TILE, Contribution(drive, 0, np.where(seen, height, np.nan).astype(np.float32),
                                       np.where(seen, 2.0, 0.0).astype(np.float32), prob, {}))
    (mosaic,) = drive_layers(store)
    merged = fuse(mosaic)
    report = {r["drive"]: r for r in merged.alignment}
    relative = np.subtract(report["b"]["tilt_cm_per_m"], report["a"]["tilt_cm_per_m"])  # (east, north)
    assert relative == pytest.approx([0.0, -1.0], abs=0.02)  # b's tilt taken out against a's
    fitted = merged.height[mapped]
    x = np.column_stack([np.ones(mapped.sum()), north_m[mapped], cols[mapped]])
    plane, *_ = np.linalg.lstsq(x, fitted.astype(np.float64), rcond=None)
    assert plane[1] == pytest.approx(0.005, abs=2e-4)  # the mean of the two tilts
    assert np.abs(fitted - x @ plane).max() < 0.002  # holes included: no step where one drive filled the other
