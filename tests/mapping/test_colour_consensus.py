"""The colour of a vertex from views without semantics (mapping.fits.colour_consensus): the views that agree, not
the mean of all. Synthetic scene: tests/mapping/synthetic_road_scene.py."""

import dataclasses

import numpy as np
import pytest

from mapping.fits.colour_consensus import ColourReads, consensus, proximity_weight
from mapping.fits.vertex_observations import VertexObservations, observe_keyframe
from mapping.method.road_mesh import build_road_mesh
from tests.mapping.synthetic_road_scene import make_scene

GROUND = np.array([0.30, 0.34, 0.45], np.float32)  # blue-grey asphalt
CAR = np.array([0.85, 0.10, 0.08], np.float32)  # a red car standing in front of it in some views


def _saturation(rgb: np.ndarray) -> float:
    return float((rgb.max() - rgb.min()) / rgb.max())


def test_the_views_that_see_the_ground_outvote_a_car_standing_in_front_of_it_in_some():
    rng = np.random.default_rng(0)
    reads = ColourReads()
    ground = GROUND + rng.normal(0, 0.01, (5, 3)).astype(np.float32)
    reads.append(np.zeros(5, np.int64), 0, ground, np.ones(5))  # vertex 0: five views see the ground ...
    reads.append(np.zeros(3, np.int64), 0, np.tile(CAR, (3, 1)), np.ones(3))  # ... three the car in front of it
    reads.append(np.ones(2, np.int64), 0, np.tile(GROUND, (2, 1)), np.ones(2))  # vertex 1: the ground only
    agreed = consensus(reads, 1, 0.08)
    assert agreed.key.tolist() == [0, 1] and agreed.inliers.tolist() == [5, 2] and agreed.reads.tolist() == [8, 2]
    np.testing.assert_allclose(agreed.colour[0], ground.mean(0), atol=1e-3)  # the ground views' mean (float16 colours)
    mean = np.concatenate([ground, np.tile(CAR, (3, 1))]).mean(0)
    assert np.abs(mean - GROUND).mean() > 0.1  # the plain mean is a smear of the car ...
    assert abs(_saturation(agreed.colour[0]) - _saturation(GROUND)) < 0.03  # ... the consensus keeps the colour


def test_nearer_views_weigh_more_so_a_few_near_ones_outvote_more_far_ones():
    reads = ColourReads()
    near, far = proximity_weight(np.array([3.0, 4.0]), 5.0), proximity_weight(np.array([18.0, 20.0, 22.0]), 5.0)
    reads.append(np.zeros(2, np.int64), 0, np.tile(GROUND, (2, 1)), near)
    reads.append(np.zeros(3, np.int64), 0, np.tile(CAR, (3, 1)), far)  # far views: the car hides the vertex
    np.testing.assert_allclose(consensus(reads, 1, 0.08).colour[0], GROUND, atol=1e-3)  # colours kept as float16
    assert len(consensus(ColourReads(), 1, 0.08).key) == 0


@pytest.fixture(scope="module")
def scene():
    return make_scene(length_m=20.0, width=96, height=54, rate_hz=10.0)


def test_a_thing_in_one_views_image_does_not_reach_the_colours_of_views_without_semantics(scene):
    mesh = build_road_mesh(scene.trajectory, 3.0, 0.2, scene.reference_height_m)
    points = np.concatenate([mesh.xy, scene.surface.height(mesh.xy[:, 0], mesh.xy[:, 1])[:, None]], 1)
    ids = np.arange(mesh.num_vertices)
    keyframes = [dataclasses.replace(kf, semantics=None) for kf in scene.keyframes if kf.camera == "front"][:6]
    painted = keyframes[3].image.copy()
    painted[30:, 30:60] = (230, 20, 20)  # something red standing on the road in front of view 3 only
    keyframes[3] = dataclasses.replace(keyframes[3], image=painted)
    names = sorted(scene.cameras)
    c = names.index("front")
    mean, agreed, clean = (VertexObservations.empty(mesh.num_vertices, names, consensus=kept)
                           for kept in (False, True, False))
    for kf in keyframes:
        for obs in (mean, agreed):
            observe_keyframe(obs, ids, points, kf, scene.cameras[kf.camera])
    for kf in keyframes[:3] + keyframes[4:]:
        observe_keyframe(clean, ids, points, kf, scene.cameras[kf.camera])
    agreed.fold_consensus(0.08)
    # the vertices the red thing covers in view 3 and at least 3 other views see
    hit = VertexObservations.empty(mesh.num_vertices, names)
    observe_keyframe(hit, ids, points, keyframes[3], scene.cameras[keyframes[3].camera])
    red = hit.colour_mean(hit.seen)[:, c, 0] > 0.8
    covered = hit.seen[red][clean.colour_count[hit.seen[red], c] >= 3]
    assert len(covered) > 20
    off_mean = np.abs(mean.colour_mean(covered)[:, c] - clean.colour_mean(covered)[:, c]).mean(-1)
    off_agreed = np.abs(agreed.colour_mean(covered)[:, c] - clean.colour_mean(covered)[:, c]).mean(-1)
    assert np.median(off_mean) > 0.05 and np.median(off_agreed) < 0.02, (np.median(off_mean), np.median(off_agreed))
    assert agreed.consensus_rejected >= len(covered) and agreed.consensus_reads is None
    # elsewhere the consensus is about the mean (a mean weighted by nearness, of the views that agree)
    calm = np.setdiff1d(clean.seen, hit.seen)
    calm = calm[clean.colour_count[calm, c] >= 2]
    gap = np.abs(agreed.colour_mean(calm)[:, c] - mean.colour_mean(calm)[:, c]).mean(-1)
    assert np.median(gap) < 0.005 and np.percentile(gap, 95) < 0.03, (np.median(gap), np.percentile(gap, 95))
