"""Keyframes without semantics (a log without masks and no segmentation model): the fits map colour and
elevation from them and train no semantics on them; a map with none has no semantics at all, a mixed one has
them only where a view with a mask labelled it. Synthetic scene (tests/mapping/synthetic_road_scene.py); the
real logs and the command: test_reconstruct_command.py, the live worker: test_mapping_worker.py, the occlusion
test itself: test_lidar_occlusion.py."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from daemon.spine.mapper_config import FaithfulFitConfig
from daemon.spine.semantic_classes import NUM_MAP_CLASSES, SemanticClass
from mapping.fits.reconstruction import reconstruct
from mapping.fits.vertex_observations import VertexObservations, observe_keyframe
from mapping.method.road_map import NO_LABEL
from mapping.method.road_mesh import build_road_mesh
from mapping.method.scene_data import StandingPoints
from mapping.outputs.map_export import vertex_labels
from mapping.outputs.map_metrics import PSNR_PIXELS
from tests.mapping.synthetic_road_scene import make_scene
from tests.mapping.test_mapping_reconstruction import CONFIG


@pytest.fixture(scope="module")
def scene():
    return make_scene(length_m=20.0, width=96, height=54, rate_hz=10.0)


def _without_semantics(keyframes, which=lambda kf: True):
    return [dataclasses.replace(kf, semantics=None) if which(kf) else kf for kf in keyframes]


def test_a_keyframe_without_semantics_gives_every_vertex_in_view_its_colour_and_no_label(scene):
    mesh = build_road_mesh(scene.trajectory, 3.0, 0.2, scene.reference_height_m)
    points = np.concatenate([mesh.xy, scene.surface.height(mesh.xy[:, 0], mesh.xy[:, 1])[:, None]], 1)
    ids = np.arange(mesh.num_vertices)
    kf = scene.keyframes[0]
    # a mask that marks the left half of the image as an obstacle: with it those vertices get no colour
    mask = kf.semantics.copy()
    mask[:, : mask.shape[1] // 2] = SemanticClass.OBSTACLE
    masked, maskless = (VertexObservations.empty(mesh.num_vertices, sorted(scene.cameras)) for _ in range(2))
    observe_keyframe(masked, ids, points, dataclasses.replace(kf, semantics=mask), scene.cameras[kf.camera])
    labelled = observe_keyframe(maskless, ids, points, dataclasses.replace(kf, semantics=None),
                                scene.cameras[kf.camera])
    assert labelled == 0 and maskless.label_counts.sum() == 0
    assert set(masked.seen) < set(maskless.seen) and len(maskless.seen) > 1.5 * len(masked.seen)
    both = masked.seen
    assert np.array_equal(masked.colour_sum[both], maskless.colour_sum[both])  # the same colours where both read


def test_keyframes_without_masks_map_colour_and_elevation_and_no_semantics(scene, tmp_path):
    keyframes = _without_semantics(scene.keyframes)
    result = reconstruct(keyframes, scene.cameras, scene.trajectory, scene.lidar, CONFIG, scene.reference_height_m,
                         tmp_path, gt=scene.gt, holdout_every=5, progress=False)
    m = result.metrics
    assert m["semantics"].startswith(f"unavailable: {m['keyframes_train']} of {m['keyframes_train']} training "
                                     "keyframes have no mask and no segmentation model is configured")
    assert m["keyframes_without_semantics"] == len(keyframes)
    assert m["maskless_rejection"].startswith("none: no Lidar standing points") and m["maskless_hidden_pct"] is None
    assert m["miou_pct"] is None and m["iou_pct"] is None and m["miou_mask_pct"] is None
    assert m["psnr_pixels"] == PSNR_PIXELS[frozenset({False})] and m["psnr_db"] > 18.0
    assert m["elev_mae_gt_cm"] < 3.0 and m["vertices_observed"] > 1000
    assert result.road_map.semantic_logits is None  # not a map of untrained logits
    assert not (tmp_path / "bev_semantics.png").exists() and not (tmp_path / "bev_semantics.npy").exists()
    assert "bev_semantics.npy" not in result.files
    assert json.loads((tmp_path / "bev.json").read_text())["semantics"] is False
    for name in ("bev_rgb_front.png", "bev_rgb_left.png", "bev_elevation.npy", "bev_elevation.png", "mesh.ply"):
        assert (tmp_path / name).stat().st_size > 0
    assert "semantic_logits" not in torch.load(tmp_path / "checkpoint.pt")
    assert (vertex_labels(result.road_map) == NO_LABEL).all()


@pytest.mark.parametrize("faithful", [False, True], ids=["fast", "faithful"])
def test_a_mixed_drive_takes_semantics_from_the_views_with_masks_only(scene, faithful):
    keyframes = _without_semantics(scene.keyframes, lambda kf: kf.camera == "left")  # the left camera has none
    config = CONFIG.model_copy(update={"faithful_fit": FaithfulFitConfig(epochs=1)})
    result = reconstruct(keyframes, scene.cameras, scene.trajectory, scene.lidar, config, scene.reference_height_m,
                         gt=scene.gt, holdout_every=5, faithful=faithful, progress=False)
    m, road_map = result.metrics, result.road_map
    missing = sum(kf.camera == "left" for kf in keyframes)
    assert m["semantics"].startswith("partial: ") and "training keyframes have no mask" in m["semantics"]
    assert m["keyframes_without_semantics"] == missing and m["miou_pct"] is not None
    assert m["psnr_pixels"] == PSNR_PIXELS[frozenset({True, False})]
    observed = road_map.observed > 0
    only_left = observed & ~road_map.labelled  # seen, but only by the camera without masks
    assert road_map.labelled[observed].mean() > 0.3 and only_left.sum() > 100
    labels = vertex_labels(road_map)
    assert (labels[only_left] == NO_LABEL).all() and (labels[road_map.labelled] < NUM_MAP_CLASSES).all()
    all_masked = reconstruct(scene.keyframes, scene.cameras, scene.trajectory, scene.lidar, config,
                             scene.reference_height_m, gt=scene.gt, holdout_every=5, faithful=faithful, progress=False)
    # the same held-out views (here only the front camera's have masks to score): the maskless views spoil nothing
    assert m["miou_pct"] > 0.9 * all_masked.metrics["miou_pct"]


@pytest.mark.parametrize("faithful", [False, True], ids=["fast", "faithful"])
def test_both_fits_leave_out_the_surface_behind_what_the_lidar_saw_standing(scene, faithful):
    """A wall across the road 12 m on, seen standing by every scan: the views without masks lose what lies
    behind it, and say so; without the standing points they lose nothing."""
    wall = np.array([(12.0, y, z) for y in np.arange(-5, 5.01, 0.2) for z in np.arange(0.5, 2.51, 0.2)], np.float32)
    standing = StandingPoints.of([(t, wall) for t in np.arange(0.0, 4.01, 0.1)])
    keyframes = _without_semantics(scene.keyframes)
    config = CONFIG.model_copy(update={"faithful_fit": FaithfulFitConfig(epochs=1)})
    runs = [reconstruct(keyframes, scene.cameras, scene.trajectory, scene.lidar, config, scene.reference_height_m,
                        holdout_every=5, faithful=faithful, progress=False, lidar_standing=s) for s in (standing, None)]
    tested, untested = (r.metrics for r in runs)
    assert tested["maskless_rejection"].startswith("lidar occlusion") and tested["maskless_views_unchecked"] == 0
    assert 5 < tested["maskless_hidden_pct"] < 95 and untested["maskless_hidden_pct"] is None
    behind = runs[1].road_map.mesh.xy[:, 0] > 13.0  # the views from beyond the wall still see it
    assert (runs[0].road_map.observed[behind] > 0).sum() < (runs[1].road_map.observed[behind] > 0).sum()
