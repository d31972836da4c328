"""The map's files as a user opens them: the PNGs' colours, the GeoTIFFs' place on the earth, the GLB's up axis,
the origin in the metadata. One small synthetic drive reconstructed once, exported through reconstruct()."""

import json
import os
import shutil
import struct
import subprocess

import cv2
import numpy as np
import pytest
import rasterio
import trimesh
from rasterio.warp import transform

from daemon.spine.local_frame import LocalFrame
from daemon.spine.semantic_classes import CLASS_COLOURS, MAP_CLASSES, SemanticClass
from mapping.fits.reconstruction import reconstruct
from mapping.live import map_tiles
from mapping.live.final_map import FinalMapMetadata, TileStore, write_final_map
from mapping.method.road_map import NO_LABEL
from mapping.outputs.map_annotation import MIN_MAP_PX, nice_length_m
from mapping.outputs.map_geotiff import local_crs
from tests.daemon_fixtures import REPO
from tests.mapping.synthetic_road_scene import make_scene
from tests.mapping.test_mapping_reconstruction import CONFIG
from tests.mapping.test_mapping_worker import _raster

NODE_MODULES = REPO / "tests" / ".node" / "node_modules"  # scripts/install.sh puts the glTF validator there
VALIDATE_GLB = """
const validator = require("gltf-validator");
validator.validateBytes(new Uint8Array(require("fs").readFileSync(process.argv[1])))
    .then((report) => console.log(JSON.stringify(report.issues)))
    .catch((error) => { console.error(String(error)); process.exit(1); });
"""
VIRIDIS_LOW, VIRIDIS_HIGH = (68, 1, 84), (253, 231, 37)  # RGB of the colour map's ends
ORIGIN = LocalFrame(48.137, 11.575, 520.0)  # the drive's ENU origin: at 520 m the CRS's scale matters (8 cm/km)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    scene = make_scene(length_m=12.0, width=64, height=36, rate_hz=10.0)
    out = tmp_path_factory.mktemp("map")
    result = reconstruct(scene.keyframes, scene.cameras, scene.trajectory, scene.lidar, CONFIG,
                         scene.reference_height_m, out, holdout_every=5, progress=False, origin=ORIGIN)
    return result, out


def _png_rgb(path):
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def test_elevation_png_shows_the_highest_cell_yellow_and_the_lowest_purple(exported):
    _, out = exported
    elevation = np.flipud(np.load(out / "bev_elevation.npy"))  # the PNG is north up: row 0 north
    png = _png_rgb(out / "bev_elevation.png").astype(int)
    assert png.shape[:2] == elevation.shape
    top = np.unravel_index(np.nanargmax(elevation), elevation.shape)
    low = np.unravel_index(np.nanargmin(elevation), elevation.shape)
    assert np.abs(png[top] - VIRIDIS_HIGH).max() <= 6, png[top]  # yellow, not cyan (red and blue swapped)
    assert np.abs(png[low] - VIRIDIS_LOW).max() <= 6, png[low]
    assert (png[~np.isfinite(elevation)] == 0).all()  # unmapped cells black


def _metres_apart(frame: LocalFrame, lat_a, lon_a, lat_b, lon_b) -> np.ndarray:
    """Horizontal distance (m) between geodetic points near `frame`'s origin, at its height."""
    a = frame.geodetic_to_enu(lat_a, lon_a, np.full(np.shape(lat_a), frame.alt_m))
    b = frame.geodetic_to_enu(lat_b, lon_b, np.full(np.shape(lat_b), frame.alt_m))
    return np.hypot(*(a - b)[..., :2].T)


def test_bev_json_carries_the_origin_and_the_crs(exported):
    _, out = exported
    meta = json.loads((out / "bev.json").read_text())
    assert meta["origin_lat_lon_alt"] == [ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m]
    assert meta["crs"] == local_crs(ORIGIN) and meta["crs"].startswith("+proj=tmerc +lat_0=48.137")


def test_elevation_geotiff_places_a_mapped_cell_at_its_latitude_and_longitude(exported):
    _, out = exported
    grid = np.load(out / "bev_elevation.npy")
    meta = json.loads((out / "bev.json").read_text())
    (x0, y0), res = meta["origin_xy"], meta["resolution_m"]
    with rasterio.open(out / "bev_elevation.tif") as tif:
        assert tif.dtypes == ("float32",) and np.isnan(tif.nodata) and tif.units == ("metre",)
        data = tif.read(1)
        np.testing.assert_array_equal(data, np.flipud(grid))  # north up, NaN where not mapped
        i, j = np.argwhere(np.isfinite(grid))[len(np.argwhere(np.isfinite(grid))) // 3]
        x, y = x0 + j * res, y0 + i * res  # the cell's centre in the local frame
        row, col = tif.index(x, y)
        assert data[row, col] == grid[i, j]
        (lon,), (lat,) = transform(tif.crs, "EPSG:4326", [x], [y])
    true_lat, true_lon, _ = ORIGIN.enu_to_geodetic([x, y, float(grid[i, j])])
    assert _metres_apart(ORIGIN, lat, lon, true_lat, true_lon) < 1e-3


def test_the_crs_agrees_with_the_local_frame_kilometres_from_the_origin():
    """Ground points at the origin's height (a road through the country), ENU -> lat/lon by the project's own
    local frame and by the GeoTIFFs' CRS (PROJ, inside rasterio)."""
    for frame in (ORIGIN, LocalFrame(-33.9, 151.2, 40.0), LocalFrame(64.1, -21.9, 1200.0)):
        angle = np.linspace(0, 2 * np.pi, 12, endpoint=False)
        for d, tolerance_m in ((1000.0, 0.001), (5000.0, 0.005)):
            on_ground = frame.enu_to_geodetic(np.stack([d * np.cos(angle), d * np.sin(angle), 0 * angle], 1))
            enu = frame.geodetic_to_enu(on_ground[0], on_ground[1], np.full(12, frame.alt_m))
            lon, lat = transform(local_crs(frame), "EPSG:4326", enu[:, 0].tolist(), enu[:, 1].tolist())
            assert _metres_apart(frame, lat, lon, on_ground[0], on_ground[1]).max() < tolerance_m, (frame, d)


def test_semantic_geotiff_has_the_class_ids_and_their_colours(exported):
    _, out = exported
    labels = np.load(out / "bev_semantics.npy")
    with rasterio.open(out / "bev_semantics.tif") as tif:
        assert tif.dtypes == ("uint8",) and tif.nodata == NO_LABEL and tif.crs is not None
        np.testing.assert_array_equal(tif.read(1), np.flipud(labels))
        table = tif.colormap(1)
    for c in SemanticClass:
        assert table[int(c)][:3] == tuple(CLASS_COLOURS[c])
    assert table[NO_LABEL][3] == 0  # unlabelled cells transparent


def test_rgb_geotiff_matches_the_png_and_masks_the_unmapped_cells(exported):
    _, out = exported
    elevation = np.load(out / "bev_elevation.npy")
    with rasterio.open(out / "bev_rgb_front.tif") as tif:
        assert tif.count == 3 and tif.crs is not None
        np.testing.assert_array_equal(np.moveaxis(tif.read(), 0, 2), _png_rgb(out / "bev_rgb_front.png"))
        np.testing.assert_array_equal(tif.read_masks(1) > 0, np.flipud(np.isfinite(elevation)))


def test_the_live_final_map_has_geotiffs_and_the_origin_in_its_metadata(tmp_path):
    tiles, n = tmp_path / "tiles", 10
    map_tiles.write_window(tiles, n, 0, _raster(-2, -5, 5, 30, 1.0, np.ones((5, 30), bool)), ["cam"])
    map_tiles.write_window(tiles, n, 1, _raster(23, 40, 5, 12, 2.0, np.ones((5, 12), bool)), ["cam"])
    final = write_final_map(tmp_path / "final", TileStore(tiles, n, 0.1, ["cam"]), FinalMapMetadata(
        windows=[{"status": "done"}], config={}, distance_m=10.0,
        origin_lat_lon_alt=[ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m]))
    meta = FinalMapMetadata.read(final)
    assert meta.crs == local_crs(ORIGIN) and meta.origin_lat_lon_alt == [ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m]
    assert not list(final.glob("*.tmp*")) and not list(final.glob("*.msk"))
    for name in ("bev_rgb_cam", "bev_semantics", "bev_elevation"):  # each overview beside its annotated one
        plain, shown = _png_rgb(final / f"{name}.png"), _png_rgb(final / f"{name}_annotated.png")
        assert shown.shape[1] > plain.shape[1] and shown.shape[0] >= plain.shape[0]
    doc, _ = _glb(final / "mesh.glb")
    assert doc["meshes"][0]["extras"]["roadlog"]["origin_lat_lon_alt"] == meta.origin_lat_lon_alt
    with rasterio.open(final / "bev_elevation.tif") as tif:
        assert tif.crs is not None and tif.res == (0.1, 0.1)
        assert tif.read(1)[tif.index(4.5, 2.5)] == 2.0  # global cell (25, 45) of the second window
        assert np.isnan(tif.read(1)[tif.index(4.5, 0.5)])  # between the windows: not mapped
    with rasterio.open(final / "bev_semantics.tif") as tif:
        assert tif.read(1)[tif.index(-0.3, -0.1)] == 1
    with rasterio.open(final / "bev_rgb_cam.tif") as tif:
        assert tif.read(1)[tif.index(4.5, 2.5)] == 2 and tif.read_masks(1)[tif.index(4.5, 0.5)] == 0


def _glb(path):
    """(glTF JSON, binary chunk) of a GLB file."""
    data = path.read_bytes()
    magic, version, _ = struct.unpack_from("<4sII", data)
    assert magic == b"glTF" and version == 2
    json_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + json_len])
    return doc, data[20 + json_len + 8:]


def _positions(doc, binary) -> np.ndarray:
    accessor = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    view = doc["bufferViews"][accessor["bufferView"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    assert accessor["componentType"] == 5126 and accessor["type"] == "VEC3"  # float32 x, y, z
    return np.frombuffer(binary, np.float32, accessor["count"] * 3, start).reshape(-1, 3)


def test_glb_is_y_up_by_the_gltf_spec_x_east_z_south(exported):
    """glTF's +Y is up: the road's heights are the GLB's Y, its north is -Z; the PLY stays in the ENU frame."""
    _, out = exported
    doc, binary = _glb(out / "mesh.glb")
    for node in doc["nodes"]:  # no root rotation: the vertices themselves are Y-up
        assert "rotation" not in node and "matrix" not in node
    extras = doc["meshes"][0]["extras"]["roadlog"]
    assert extras["origin_lat_lon_alt"] == [ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m] and "Y up" in extras["axes"]
    glb = _positions(doc, binary).astype(np.float64)
    enu = trimesh.load(out / "mesh.ply", process=False).vertices
    np.testing.assert_allclose(glb, np.stack([enu[:, 0], enu[:, 2], -enu[:, 1]], 1), atol=1e-4)
    extent = glb.max(0) - glb.min(0)
    assert extent[1] < 0.1 * min(extent[0], extent[2])  # a road lies flat: its thin axis is Y


def test_glb_passes_the_khronos_gltf_validator(exported):
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the Khronos glTF validator (npm gltf-validator) runs on it")
    if not (NODE_MODULES / "gltf-validator").is_dir():
        pytest.skip(f"the Khronos glTF validator is not installed: npm install --prefix {NODE_MODULES.parent} "
                    "gltf-validator (scripts/install.sh does when npm is there)")
    _, out = exported
    run = subprocess.run([shutil.which("node"), "-e", VALIDATE_GLB, str(out / "mesh.glb")], capture_output=True,
                         text=True, timeout=60, env=os.environ | {"NODE_PATH": str(NODE_MODULES)})
    assert run.returncode == 0, run.stderr
    issues = json.loads(run.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]


def _longest_black_run(rows: np.ndarray) -> int:
    best = 0
    for row in (rows.max(axis=2) < 40):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], row.astype(np.int8), [0]])))
        best = max([best] + list(edges[1::2] - edges[::2]))
    return int(best)


def test_annotated_pngs_show_the_map_with_legend_colour_bar_scale_and_north(exported):
    _, out = exported
    res = json.loads((out / "bev.json").read_text())["resolution_m"]
    plain = _png_rgb(out / "bev_semantics.png")
    shown = _png_rgb(out / "bev_semantics_annotated.png")
    zoom = MIN_MAP_PX // max(plain.shape[:2])
    assert zoom > 1  # a small map is enlarged, whole pixels per cell
    np.testing.assert_array_equal(shown[:plain.shape[0] * zoom:zoom, :plain.shape[1] * zoom:zoom], plain)
    panel = shown[:, plain.shape[1] * zoom + 1:]
    swatches = {tuple(v) for v in panel.reshape(-1, 3)}
    assert all(tuple(CLASS_COLOURS[c]) in swatches for c in MAP_CLASSES)  # the legend's colours
    # the scale bar: its edge rows are black over its length, a round number of metres at the map's scale
    px_per_m = zoom / res
    bar_px = _longest_black_run(panel)
    assert abs(bar_px - nice_length_m(bar_px / px_per_m + 0.01) * px_per_m) <= 1.5 and bar_px > 40
    elevation = _png_rgb(out / "bev_elevation_annotated.png").astype(int)
    bar = elevation[:, plain.shape[1] * zoom + 1:]
    high = np.argwhere(np.abs(bar - VIRIDIS_HIGH).max(axis=2) <= 6)
    low = np.argwhere(np.abs(bar - VIRIDIS_LOW).max(axis=2) <= 6)
    assert len(high) and len(low) and high[:, 0].max() < low[:, 0].min()  # the colour bar: high end on top


def test_scale_bar_lengths_are_round():
    assert [nice_length_m(v) for v in (0.37, 1.0, 4.9, 7.0, 19.0, 230.0)] == [0.2, 1.0, 2.0, 5.0, 10.0, 200.0]
