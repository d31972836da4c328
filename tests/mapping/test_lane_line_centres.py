"""Lane markings on the centres of lines the views blurred (mapping.fits.lane_line_centres), on frequencies made by
hand and on labels read through observe_keyframe from coarse views of thin stripes."""

import numpy as np
import pytest

import mapping.outputs.map_metrics as map_metrics
from daemon.spine.semantic_classes import SemanticClass
from mapping.fits.lane_line_centres import OPPOSITE_NEIGHBOURS, line_centre_excess, raise_line_centres
from mapping.fits.observation_fit import semantic_logits_from_counts
from mapping.fits.vertex_observations import MeshFootprint, VertexObservations, observe_keyframe
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.road_mesh import build_road_mesh, locate
from mapping.method.scene_data import CameraModel, Keyframe

LANE, ROAD = SemanticClass.LANE_MARKING, SemanticClass.ROAD


def _mesh():
    """A 0.1 m mesh 4 m wide along x."""
    return build_road_mesh(HorizontalTrack(np.array([0.0, 10.0]), np.array([[-3.0, 0.0, 1.5], [3.0, 0.0, 1.5]])),
                           2.0, 0.1, 1.5)


def _frequencies(lane: np.ndarray) -> np.ndarray:
    p = np.zeros((len(lane), 5))
    p[:, LANE], p[:, ROAD] = lane, 1.0 - lane
    return p


def test_the_opposite_neighbour_slots_face_each_other_through_the_vertex():
    """OPPOSITE_NEIGHBOURS names road_mesh's neighbour columns by position: each pair lies on a line through the
    vertex, one mesh side either way, and the three pairs are the lattice's three directions."""
    mesh = _mesh()
    inner = np.flatnonzero((mesh.neighbours >= 0).all(1))
    directions = []
    for a, b in OPPOSITE_NEIGHBOURS:
        to_a, to_b = (mesh.xy[mesh.neighbours[inner, k]] - mesh.xy[inner] for k in (a, b))
        np.testing.assert_allclose(to_a, -to_b, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(to_a, axis=1), 0.1, rtol=1e-9)
        directions.append(np.degrees(np.arctan2(to_a[0, 1], to_a[0, 0])) % 180.0)
    assert sorted(np.round(directions)) == [0.0, 60.0, 120.0]


def test_a_blurred_thin_line_is_raised_on_its_centre_and_nothing_else_moves():
    """A 14 cm line at 10 degrees to the mesh's rows, blurred to a 40 % peak (road wins everywhere), becomes lane
    along its centre; a wide marking (a plateau and its two edges), uniform road and unread vertices keep their
    frequencies exactly."""
    mesh = _mesh()
    across = np.array([-np.sin(np.radians(10.0)), np.cos(np.radians(10.0))])
    d_thin = mesh.xy @ across - 0.8  # signed distance to the thin line's centre (y from -0.1 to 1.7 m)
    thin = 0.4 * np.exp(-0.5 * (d_thin / 0.08) ** 2)
    wide = 0.9 * np.clip((0.25 - np.abs(mesh.xy[:, 1] + 1.2)) / 0.1, 0.0, 1.0)  # a 0.9 plateau 30 cm wide at
    # y = -1.2 m, its edges ramps 10 cm wide
    p = _frequencies(np.maximum(thin, wide))
    known = np.ones(mesh.num_vertices, bool)
    known[mesh.xy[:, 0] > 2.5] = False  # unread (no side of a ridge either)
    raised = raise_line_centres(p, mesh.neighbours, known, LANE, 2.0)
    np.testing.assert_allclose(raised.sum(1)[known], 1.0)
    assert (p[mesh.xy[:, 1] > -0.5].argmax(1) == ROAD).all()
    centre = known & (np.abs(d_thin) < 0.025) & (np.abs(mesh.xy[:, 0]) < 2.0)
    assert centre.sum() > 20 and (raised[centre].argmax(1) == LANE).mean() > 0.8
    moved = np.abs(raised - p).max(1) > 0
    assert moved.sum() > 20 and (np.abs(d_thin[moved]) < 0.06).all(), "only the thin line's centre moves"
    assert not moved[~known].any() and not moved[mesh.xy[:, 1] < -0.6].any()  # the wide marking, unread vertices
    assert line_centre_excess(p[:, LANE], mesh.neighbours, known)[mesh.xy[:, 1] < -0.6].max() == 0
    assert (raise_line_centres(p, mesh.neighbours, known, LANE, 0.0) == p).all()


def _thin_stripes_miou(gain: float, width_m: float, pixel_m: float, views: int) -> dict[str, float]:
    """IoU (lane marking, road) of the labels interpolated between the vertices of a 0.1 m mesh that `views` cameras
    looking straight down, `pixel_m` pixels on the ground at random sub-pixel offsets, read on `width_m` stripes
    every 0.9 m at 20 degrees to the mesh's rows (each view's labels taken at its pixel centres, as a segmenter's)."""
    mesh = _mesh()
    focal, half = 10.0 / pixel_m, int(np.ceil(1.8 / pixel_m))  # each view covers the 3 m square scored, and more
    size = 2 * half + 1
    camera = CameraModel("down", np.array([[focal, 0, half], [0, focal, half], [0, 0, 1]]), (0.0,) * 5, size, size)
    across = np.array([np.cos(np.radians(20.0)), np.sin(np.radians(20.0))])

    def stripes(xy: np.ndarray) -> np.ndarray:
        return np.where(np.mod(xy @ across, 0.9) < width_m, LANE, ROAD).astype(np.uint8)

    rng = np.random.default_rng(0)
    obs = VertexObservations.empty(mesh.num_vertices, ["down"])
    points = np.concatenate([mesh.xy, np.zeros((mesh.num_vertices, 1))], 1)
    footprint = MeshFootprint.of(mesh.neighbours, 4)
    v, u = np.mgrid[0:size, 0:size]
    for _ in range(views):
        shift = rng.uniform(-pixel_m, pixel_m, 2)
        pose = np.eye(4)
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down
        pose[:3, 3] = [shift[0], shift[1], 10.0]
        ground = np.stack([shift[0] + (u - half) * pixel_m, shift[1] + (half - v) * pixel_m], -1).reshape(-1, 2)
        kf = Keyframe("down", 0.0, pose, np.zeros((size, size, 3), np.uint8), stripes(ground).reshape(size, size))
        observe_keyframe(obs, np.arange(mesh.num_vertices), points, kf, camera, footprint)
    logits = semantic_logits_from_counts(obs.label_counts, mesh.neighbours, gain).numpy()
    cells = rng.uniform(-1.5, 1.5, (20_000, 2))
    tri, w, inside = locate(mesh, cells)
    pred = (logits[tri[inside]] * w[inside][..., None]).sum(1).argmax(1)
    iou = map_metrics.iou_pct(map_metrics.confusion(pred, stripes(cells[inside]), np.ones(len(pred), bool)))
    return {"lane": iou["lane_marking"], "road": iou["road"]}


@pytest.mark.parametrize("width_m", [0.12, 0.16])
def test_thin_stripes_seen_through_coarse_pixels_are_mapped_with_the_gain(width_m):
    """Stripes narrower than the views' 30 cm pixels (the edge line 9 m beside the car): the plain label frequencies
    lose most of the stripes to the road around them; raised on their centres, the stripes are mapped."""
    plain = _thin_stripes_miou(0.0, width_m, 0.3, 24)
    raised = _thin_stripes_miou(2.0, width_m, 0.3, 24)
    assert raised["lane"] > plain["lane"] + 5.0, (plain, raised)
    assert raised["road"] > plain["road"] - 1.0, (plain, raised)


def test_sharp_views_of_a_thin_stripe_cost_little():
    """Views whose pixels (1 cm) resolve a 14 cm stripe read it at full frequency: its centre is a ridge all the
    same and is raised, which widens the stripe a little where the logits are interpolated (the price of the gain
    on blurred lines): lane IoU within 3 points of the plain frequencies', and still above 90 %."""
    plain = _thin_stripes_miou(0.0, 0.14, 0.01, 2)
    raised = _thin_stripes_miou(2.0, 0.14, 0.01, 2)
    assert plain["lane"] - 3.0 < raised["lane"] and raised["lane"] > 90.0, (plain, raised)
