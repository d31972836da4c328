"""The camera-only elevation: the plane sweep on a synthetic scene whose true height is known, and the
reconstruction without Lidar against the flat sheet."""

import json

import numpy as np
import pytest
import torch

from mapping.fits.photometric_elevation import SweepSettings, _peaks, lattice_nodes, sweep_heights
from mapping.fits.reconstruction import reconstruct
from mapping.method.road_map import new_road_map, variant_for
from mapping.method.road_mesh import build_road_mesh
from tests.mapping.synthetic_road_scene import Surface, make_scene
from tests.mapping.test_mapping_reconstruction import CONFIG
from tests.mapping.test_reconstruct_command import undocumented_metrics

# a steep crossfall and no along-track relief: z0 (from the trajectory) is right on the centre line and
# 20 cm off at the corridor's edges, which only the images can tell
SURFACE = Surface(slope=0.03, crossfall=0.05, bump_m=0.0)


@pytest.fixture(scope="module")
def scene():
    return make_scene(length_m=16.0, width=128, height=72, rate_hz=5.0, surface=SURFACE)


def _road_map(scene, lattice_m: float):
    mesh = build_road_mesh(scene.trajectory, 4.0, 0.2, scene.reference_height_m)
    return new_road_map(mesh, variant_for(None), sorted(scene.cameras), 32, 2, 16, 22, 8, 128, 40.0, lattice_m,
                        torch.Generator().manual_seed(0))


def _keyframe_s(scene):
    return np.array([float(scene.trajectory.horizontal_distance_at(k.timestamp)) for k in scene.keyframes])


def test_peaks_refine_the_best_height_by_a_parabola_and_find_the_second_peak():
    heights = np.arange(-0.1, 0.101, 0.02)
    ncc = np.exp(-((heights - 0.013) / 0.03) ** 2)[None] * 0.9
    ncc[0, 0] = 0.4  # a second peak far away
    best, peak, second, inner = _peaks(ncc, np.ones_like(ncc, bool), heights, 3)
    assert abs(best[0] - 0.013) < 0.004 and peak[0] == pytest.approx(ncc.max()) and second[0] == pytest.approx(0.4)
    assert inner[0]


def test_the_sweep_recovers_the_crossfall_the_trajectory_cannot_see(scene):
    road_map = _road_map(scene, 0.5)
    lattice = lattice_nodes(road_map, 0.5)
    result = sweep_heights(road_map, lattice, scene.keyframes, _keyframe_s(scene), scene.cameras,
                           SweepSettings(span_m=0.3, step_m=0.02, patch_m=0.5, patch_samples=7, min_views=3))
    true = SURFACE.height(lattice.xy[:, 0], lattice.xy[:, 1]) - lattice.z0
    sure = result.confidence > 0.05
    assert sure.mean() > 0.3  # a good share of the nodes has a usable height
    error = np.abs(result.residual[sure] - true[sure])
    assert np.abs(true[sure]).mean() > 0.05  # the flat sheet is 5+ cm off there ...
    # ... the sweep a third of that (measured: median 2.4 cm, mean 3.7 cm against the flat sheet's 9.3 cm)
    assert np.median(error) < 0.35 * np.abs(true[sure]).mean() and error.mean() < 0.5 * np.abs(true[sure]).mean()


def test_a_sweep_centred_on_a_surface_reads_the_heights_around_it(scene):
    """The second, narrow sweep: centred on a given surface (here the truth raised 5 cm, tilted by the crossfall
    as the truth is), its patches on it, the heights come back over z0 and on the truth; a surface 25 cm off,
    beyond the +-10 cm range, gives (almost) no heights rather than ones on the range's edge."""
    road_map = _road_map(scene, 0.5)
    lattice = lattice_nodes(road_map, 0.5)
    mesh = road_map.mesh
    true_vertex = SURFACE.height(mesh.xy[:, 0], mesh.xy[:, 1]).astype(np.float32)
    true = SURFACE.height(lattice.xy[:, 0], lattice.xy[:, 1]) - lattice.z0
    narrow = SweepSettings(span_m=0.1, step_m=0.02, patch_m=0.5, patch_samples=7, min_views=3)
    near = sweep_heights(road_map, lattice, scene.keyframes, _keyframe_s(scene), scene.cameras, narrow,
                         true_vertex + 0.05)
    sure = near.confidence > 0
    assert sure.mean() > 0.3
    error = np.abs(near.residual[sure] - true[sure])
    assert np.median(error) < 0.02 and error.mean() < 0.03, (np.median(error), error.mean())
    assert np.allclose(near.residual[~sure], (true + 0.05)[~sure], atol=0.02)  # no height: the surface itself
    far = sweep_heights(road_map, lattice, scene.keyframes, _keyframe_s(scene), scene.cameras, narrow,
                        true_vertex + 0.25)
    assert (far.confidence > 0).mean() < 0.2 * sure.mean()


def test_camera_only_reconstruction_beats_the_flat_sheet(scene):
    runs = {ablation: reconstruct(scene.keyframes, scene.cameras, scene.trajectory, None, CONFIG,
                                  scene.reference_height_m, None, ablation=ablation, gt=scene.gt, holdout_every=5,
                                  progress=False) for ablation in (None, "no-elevation-mlp")}
    camera, flat = runs[None].metrics, runs["no-elevation-mlp"].metrics
    assert camera["photometric_sweep_wall_s"] > 0 and "photometric_sweep_wall_s" not in flat
    assert camera["elev_mae_gt_cm"] < 0.5 * flat["elev_mae_gt_cm"]


@pytest.mark.slow
def test_roadlog_reconstruct_without_lidar_beats_the_flat_sheet_on_a_simulated_drive(city_drive, tmp_path):
    """The simulated city drive (2.5 % crossfall, 15 cm kerbs) through `roadlog reconstruct --no-lidar`: the
    images' elevation against the trajectory's height extended flat sideways."""
    from mapping.offline.reconstruct_command import main

    gt = str(city_drive.with_name("city.gt.npz"))
    mae = {}
    for name, extra in (("camera", []), ("flat", ["--ablation", "no-elevation-mlp"])):
        assert main([str(city_drive), "--out", str(tmp_path / name), "--gt", gt, "--no-lidar", *extra]) == 0
        metrics = json.loads((tmp_path / name / "metrics.json").read_text())
        assert not undocumented_metrics(metrics)
        mae[name] = metrics["elev_mae_gt_cm"]
    assert mae["camera"] < 0.67 * mae["flat"], mae
