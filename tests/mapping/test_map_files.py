"""The map's files as a user opens them: the PNGs' colours, the GeoTIFFs' place on the earth, the GLB's up axis,
the origin in the metadata. One small synthetic drive reconstructed once, exported through reconstruct()."""

import cv2
import numpy as np
import pytest

from mapping.fits.reconstruction import reconstruct
from tests.mapping.synthetic_road_scene import make_scene
from tests.mapping.test_mapping_reconstruction import CONFIG

VIRIDIS_LOW, VIRIDIS_HIGH = (68, 1, 84), (253, 231, 37)  # RGB of the colour map's ends


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    scene = make_scene(length_m=12.0, width=64, height=36, rate_hz=10.0)
    out = tmp_path_factory.mktemp("map")
    result = reconstruct(scene.keyframes, scene.cameras, scene.trajectory, scene.lidar, CONFIG,
                         scene.reference_height_m, out, holdout_every=5, progress=False)
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
