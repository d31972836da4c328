import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch
import trimesh

import mapping.fits.fast_fit as fast_fit
import mapping.outputs.map_metrics as map_metrics
from daemon.spine.mapper_config import (
    FaithfulFitConfig,
    InputsConfig,
    MapperConfig,
    MeshConfig,
    RuntimeConfig,
    WindowsConfig,
)
from daemon.spine.semantic_classes import SemanticClass
from mapping.fits.faithful_fit import FaithfulOptimisation
from mapping.fits.lidar_detail import fit_lidar_detail
from mapping.fits.observation_fit import fit_elevation, semantic_logits_from_counts
from mapping.fits.reconstruction import reconstruct
from mapping.fits.vertex_observations import (
    FACE_DIRECTIONS,
    FACE_EDGES,
    MeshFootprint,
    VertexObservations,
    observe_keyframe,
    pixel_ground_length_m,
    project_points,
)
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.mesh_location import Located
from mapping.method.road_map import ABLATIONS, new_road_map, variant_for
from mapping.method.road_mesh import build_road_mesh, locate
from mapping.method.row_sparse_adam import RowSparseAdam
from mapping.method.scene_data import CameraModel, Keyframe
from mapping.outputs.map_metrics import MetricPoints, elev_error_cm, elev_mae_gt_cm, truth_cells
from tests.mapping.synthetic_road_scene import make_scene, texture

CONFIG = MapperConfig(mesh=MeshConfig(side_m=0.2, corridor_half_width_m=5.0),
                      inputs=InputsConfig(keyframe_spacing_m=0.0), runtime=RuntimeConfig(torch_threads_faithful_fit=1),
                      windows=WindowsConfig(before_m=20.0, after_m=20.0))



@pytest.fixture(scope="module")
def scene():
    return make_scene(length_m=20.0, width=96, height=54, rate_hz=10.0)


@pytest.fixture(scope="module")
def fast_run(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("map")
    result = reconstruct(scene.keyframes, scene.cameras, scene.trajectory, scene.lidar,
                         CONFIG, scene.reference_height_m, out, gt=scene.gt,
                         holdout_every=5, progress=False)
    return result, out


def _mae_at_z0_cm(road_map, gt) -> float:
    """The error against the truth of the map's initial surface (z0, from the trajectory)."""
    fitted = road_map.z_now.copy()
    road_map.z_now[:] = road_map.mesh.z0
    try:
        return elev_mae_gt_cm(road_map, gt)
    finally:
        road_map.z_now[:] = fitted


def test_loss_falls_and_elevation_error_shrinks(scene, fast_run):
    result, _ = fast_run
    m = result.metrics
    assert m["loss_last"] < 0.6 * m["loss_first"]
    start_cm = _mae_at_z0_cm(result.road_map, scene.gt)
    assert start_cm > 5.0  # the crossfall is not in the trajectory-based z0
    assert m["elev_mae_gt_cm"] < 0.75 * start_cm  # 80 steps; it reaches ~1 cm with 20 epochs
    assert m["elev_error_cm"] < 0.75 * start_cm
    assert m["psnr_db"] > 18.0 and m["miou_pct"] > 40.0
    assert m["keyframes_holdout"] > 0 and m["optimise_wall_s"] > 0 and "realtime_factor" not in m


def test_faithful_path_loss_falls_and_elevation_error_shrinks(scene):
    """The paper's computation (every window vertex through the MLPs, differentiable rendering of pixels):
    3 epochs on the tiny scene take the loss from ~1.9 to ~0.7 and the elevation error from ~11 to ~6 cm."""
    result = reconstruct(scene.keyframes, scene.cameras, scene.trajectory, scene.lidar,
                         CONFIG.model_copy(update={"faithful_fit": FaithfulFitConfig(epochs=3)}),
                         scene.reference_height_m, gt=scene.gt,
                         faithful=True, holdout_every=5, progress=False)
    m = result.metrics
    assert m["loss_last"] < 0.5 * m["loss_first"]
    start_cm = _mae_at_z0_cm(result.road_map, scene.gt)
    assert start_cm > 5.0
    assert m["elev_mae_gt_cm"] < 0.7 * start_cm and m["elev_error_cm"] < 0.7 * start_cm
    assert m["psnr_db"] > 17.0 and m["miou_pct"] > 60.0


def test_export_writes_readable_rasters_and_meshes(fast_run):
    result, out = fast_run
    files = result.files
    for name in ("bev_rgb_front.png", "bev_rgb_left.png", "bev_semantics.png", "bev_elevation.png",
                 "bev_elevation.npy", "bev_semantics.npy", "bev.json", "mesh.ply", "mesh.glb",
                 "checkpoint.pt", "metrics"):
        assert files[name].exists() and files[name].stat().st_size > 0
    elevation = np.load(files["bev_elevation.npy"])
    assert np.isfinite(elevation).mean() > 0.3
    mesh = trimesh.load(files["mesh.ply"], process=False)
    assert len(mesh.faces) > 1000 and mesh.visual.vertex_colors.shape[1] == 4
    state = torch.load(files["checkpoint.pt"])
    assert state["colour_params"].shape[1] == CONFIG.model.colour_code_dim and "elevation_mlp" in state


@pytest.mark.parametrize("ablation", sorted(ABLATIONS))
def test_ablation_switches_change_the_parameter_sets(scene, ablation):
    mesh = build_road_mesh(scene.trajectory, 3.0, 0.5, scene.reference_height_m, flat=variant_for(ablation).flat_init)
    g = torch.Generator().manual_seed(0)
    full = new_road_map(mesh, variant_for(None), ["front", "left"], 32, 2, 16, 22, 8, 128, 160.0, 0.5, g)
    rm = new_road_map(mesh, variant_for(ablation), ["front", "left"], 32, 2, 16, 22, 8, 128, 160.0, 0.5, g)
    assert full.elevation is not None and full.semantic_logits is not None
    assert set(dict(full.decoder.named_parameters())) == {f"mlps.{c}.{k}" for c in ("front", "left")
                                                            for k in ("0.weight", "0.bias", "2.weight", "2.bias")}
    names = set(dict(rm.decoder.named_parameters()))
    if ablation == "no-elevation-mlp":
        assert rm.elevation is None
    if ablation in ("no-colour-mlps", "rome"):
        assert names == set() and rm.colour_params.shape[1] == 3
    if ablation == "embedding":
        assert "embeddings" in names and not any(n.startswith("mlps") for n in names)
    if ablation == "no-semantics":
        assert rm.semantic_logits is None
    if ablation == "rome":
        assert np.ptp(rm.mesh.z0) == 0 and rm.elevation is not None
    else:
        assert np.ptp(rm.mesh.z0) > 0


def test_ablation_runs_report_what_they_lack(scene):
    cfg = CONFIG
    r = reconstruct(scene.keyframes[:24], scene.cameras, scene.trajectory, None, cfg, scene.reference_height_m,
                    None, ablation="no-semantics", progress=False)
    assert r.metrics["miou_pct"] is None and r.metrics["iou_pct"] is None and r.metrics["elev_error_cm"] is None
    assert r.metrics["psnr_db"] is not None


def test_row_sparse_adam_touches_only_the_rows_used():
    table = torch.zeros(1000, 4)
    opt = RowSparseAdam(table, lr=0.1)
    rows = torch.tensor([3, 500, 999])
    opt.step(rows, torch.ones(3, 4))
    assert torch.allclose(table[rows], torch.full((3, 4), -0.1), atol=1e-6)
    assert table.abs().sum() == pytest.approx(1.2, abs=1e-5) and opt.used == 3


def test_row_sparse_adam_matches_dense_adam_with_idle_rows():
    rng = np.random.default_rng(0)
    dense = torch.zeros(50, 3, requires_grad=True)
    dense_opt = torch.optim.Adam([dense], lr=0.01)
    table = torch.zeros(50, 3)
    sparse = RowSparseAdam(table, lr=0.01)
    for _ in range(200):
        rows = np.sort(rng.choice(50, 10, replace=False))
        g = torch.from_numpy(rng.normal(size=(10, 3)).astype(np.float32))
        full = torch.zeros(50, 3)
        full[rows] = g
        dense.grad = full
        dense_opt.step()
        sparse.step(torch.from_numpy(rows), g)
    sparse.flush()
    assert torch.allclose(table, dense.detach(), atol=2e-3)
    assert (table - dense.detach()).abs().mean() < 3e-4


def test_vertex_observations_read_the_labels_and_colours_each_vertex_was_seen_with(scene):
    mesh = build_road_mesh(scene.trajectory, 3.0, 0.2, scene.reference_height_m)
    z_true = scene.surface.height(mesh.xy[:, 0], mesh.xy[:, 1])
    points = np.concatenate([mesh.xy, z_true[:, None]], 1)
    obs = VertexObservations.empty(mesh.num_vertices, sorted(scene.cameras))
    ids = np.arange(mesh.num_vertices)
    for kf in scene.keyframes:
        observe_keyframe(obs, ids, points, kf, scene.cameras[kf.camera])
    seen = obs.seen
    assert len(seen) > 0.5 * mesh.num_vertices
    albedo, label = texture(mesh.xy[seen, 0], mesh.xy[seen, 1])
    logits = semantic_logits_from_counts(obs.label_counts[seen]).numpy()
    assert (logits.argmax(1) == label).mean() > 0.9
    front = obs.colour_count[seen, obs.camera_names.index("front")] > 0
    grey = obs.colour_mean(seen)[front, obs.camera_names.index("front")].mean(1)
    assert np.corrcoef(grey, albedo[front].mean(1))[0, 1] > 0.8  # shading and gain differ, not the pattern


def _looking_down(height_m: float) -> np.ndarray:
    """T_world_camera of a camera `height_m` above the origin looking straight down."""
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = [0.0, 0.0, height_m]
    return pose


def _stripes_miou(footprint_subdivision: int | None, width_m: float, angle_deg: float = 0.0) -> float:
    """mIoU (lane marking and road) of the labels interpolated between the vertices of a 0.1 m mesh that a camera
    looking straight down (1 cm pixels) reads on `width_m` stripes every 0.37 m, turned by `angle_deg`: at each
    vertex only (None) or over the footprints' lattice of that subdivision."""
    mesh = build_road_mesh(HorizontalTrack(np.array([0.0, 10.0]), np.array([[-3.0, 0.0, 1.5], [3.0, 0.0, 1.5]])),
                           2.0, 0.1, 1.5)
    camera = CameraModel("down", np.array([[1000.0, 0, 200], [0, 1000.0, 200], [0, 0, 1]]), (0.0,) * 5, 401, 401)
    pose = _looking_down(10.0)
    across = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])

    def stripes(xy: np.ndarray) -> np.ndarray:
        return np.where(np.mod(xy @ across, 0.37) < width_m, SemanticClass.LANE_MARKING,
                        SemanticClass.ROAD).astype(np.uint8)

    v, u = np.mgrid[0:401, 0:401]
    semantics = stripes(np.stack([(u - 200) * 0.01, (200 - v) * 0.01], -1).reshape(-1, 2)).reshape(401, 401)
    kf = Keyframe("down", 0.0, pose, np.zeros((401, 401, 3), np.uint8), semantics)
    points = np.concatenate([mesh.xy, np.zeros((mesh.num_vertices, 1))], 1)
    cells = np.random.default_rng(0).uniform(-1.5, 1.5, (20_000, 2))
    tri, w, inside = locate(mesh, cells)
    footprint = None if footprint_subdivision is None else MeshFootprint.of(mesh.neighbours, footprint_subdivision)
    obs = VertexObservations.empty(mesh.num_vertices, ["down"])
    assert observe_keyframe(obs, np.arange(mesh.num_vertices), points, kf, camera, footprint) > 0
    logits = semantic_logits_from_counts(obs.label_counts).numpy()
    pred = (logits[tri[inside]] * w[inside][..., None]).sum(1).argmax(1)
    return map_metrics.miou_pct(map_metrics.confusion(pred, stripes(cells[inside]), np.ones(len(pred), bool)))


def test_labels_read_over_the_vertex_footprint_place_edges_between_vertices():
    """15 cm stripes: the class interpolated between vertices is right more often when each vertex reads its
    whole footprint than its centre only (the centre alone puts every edge half-way between two vertices)."""
    centre, footprint = _stripes_miou(None, 0.15), _stripes_miou(2, 0.15)
    assert footprint > centre + 3.0, (centre, footprint)


@pytest.mark.parametrize("width_m, angle_deg", [(0.12, 0.0), (0.12, 20.0), (0.16, 70.0)])
def test_a_finer_footprint_lattice_keeps_thin_stripes(width_m, angle_deg):
    """The half-edge lattice (subdivision 2: 5 cm between reads) aliases a 12-16 cm stripe's share of each
    footprint; reading at the quarter points and inside the triangles (the default, 4) follows it, whichever
    way the stripes run across the mesh's rows."""
    half_edges, quarters = _stripes_miou(2, width_m, angle_deg), _stripes_miou(4, width_m, angle_deg)
    assert quarters > half_edges + 1.0, (half_edges, quarters)


def test_footprint_triangles_are_the_mesh_faces_and_each_vertex_weighs_four_per_view():
    """The triangles the footprint reads inside are the mesh's faces, each once, with the three sides its test for
    a uniform triangle reads; and a view of one label gives every vertex whose whole footprint is in view a weight
    of 4 whatever the lattice (so the label prior and the views' weights count as before)."""
    mesh = build_road_mesh(HorizontalTrack(np.array([0.0, 10.0]), np.array([[-1.0, 0.0, 1.5], [1.0, 0.0, 1.5]])),
                           0.6, 0.1, 1.5)
    triangles = set()
    for (b, c), edges in zip(FACE_DIRECTIONS, FACE_EDGES, strict=True):
        a = np.flatnonzero((mesh.neighbours[:, b] >= 0) & (mesh.neighbours[:, c] >= 0))
        corners = [a, mesh.neighbours[a, b], mesh.neighbours[a, c]]
        triangles |= {tuple(sorted(t)) for t in zip(*(k.tolist() for k in corners), strict=True)}
        sides = set()  # the edges the uniformity test reads are the triangle's three sides
        for direction, base in edges:
            end = mesh.neighbours[corners[base], direction]
            other = [k for k in range(3) if k != base and np.array_equal(corners[k], end)]
            assert len(other) == 1, (b, c, direction, base)
            sides.add(frozenset((base, other[0])))
        assert len(sides) == 3
    assert triangles == {tuple(sorted(f)) for f in mesh.faces.tolist()}
    camera = CameraModel("down", np.array([[1000.0, 0, 200], [0, 1000.0, 200], [0, 0, 1]]), (0.0,) * 5, 401, 401)
    kf = Keyframe("down", 0.0, _looking_down(10.0), np.zeros((401, 401, 3), np.uint8),
                  np.full((401, 401), SemanticClass.CURB, np.uint8))
    points = np.concatenate([mesh.xy, np.zeros((mesh.num_vertices, 1))], 1)
    inner = (mesh.neighbours >= 0).all(1)
    assert inner.sum() > 100
    for subdivision in (1, 2, 3, 4, 6):
        obs = VertexObservations.empty(mesh.num_vertices, ["down"])
        observe_keyframe(obs, np.arange(mesh.num_vertices), points, kf, camera, MeshFootprint.of(mesh.neighbours,
                                                                                                 subdivision))
        np.testing.assert_allclose(obs.label_counts[inner, SemanticClass.CURB], 4.0, rtol=1e-6)
        assert not np.delete(obs.label_counts, SemanticClass.CURB, 1).any()


def test_the_configured_footprint_lattice_is_the_one_the_fast_fit_reads(scene, monkeypatch):
    """`mapper.fast_fit.label_footprint_subdivision` reaches the footprint every keyframe is read with, and the
    lattices weigh the views alike (the total of the label counts within 2 %) while placing them differently."""
    mesh = build_road_mesh(scene.trajectory, 3.0, 0.2, scene.reference_height_m)
    made, real_of = [], MeshFootprint.of

    def footprint_of(neighbours, subdivision):
        made.append(subdivision)
        return real_of(neighbours, subdivision)

    monkeypatch.setattr(fast_fit.MeshFootprint, "of", staticmethod(footprint_of))
    counts = {}
    for subdivision in (2, 4):
        made.clear()
        road_map = new_road_map(mesh, variant_for(None), ["front", "left"], 32, 2, 16, 22, 8, 128, 160.0, 0.5,
                                torch.Generator().manual_seed(0))
        config = CONFIG.model_copy(update={"fast_fit": CONFIG.fast_fit.model_copy(
            update={"label_footprint_subdivision": subdivision})})
        counts[subdivision] = fast_fit.observe(road_map, scene.keyframes, scene.cameras, scene.trajectory, config,
                                               False, {}).label_counts
        assert made and set(made) == {subdivision}
    assert abs(counts[4].sum() / counts[2].sum() - 1.0) < 0.02
    assert not np.allclose(counts[4], counts[2])


def test_the_configured_lane_line_gain_sets_the_semantic_logits(scene):
    """`mapper.fast_fit.lane_line_gain` is the gain the fast fit's logits are raised on lane line centres with
    (mapping.fits.lane_line_centres): the same label counts, the logits of those counts at that gain, and 0 leaves
    the plain log frequencies."""
    mesh = build_road_mesh(scene.trajectory, 3.0, 0.2, scene.reference_height_m)
    logits, counts = {}, {}
    for gain in (0.0, 2.0):
        road_map = new_road_map(mesh, variant_for(None), ["front", "left"], 32, 2, 16, 22, 8, 128, 160.0, 0.5,
                                torch.Generator().manual_seed(0))
        config = CONFIG.model_copy(update={"fast_fit": CONFIG.fast_fit.model_copy(update={"lane_line_gain": gain})})
        counts[gain] = fast_fit.observe(road_map, scene.keyframes, scene.cameras, scene.trajectory, config, False,
                                        {}).label_counts
        labelled = np.flatnonzero(road_map.labelled)
        logits[gain] = road_map.semantic_logits.detach().numpy()[labelled]
        expected = semantic_logits_from_counts(counts[gain], mesh.neighbours, gain).numpy()[labelled]
        np.testing.assert_allclose(logits[gain], expected, rtol=1e-6)
    np.testing.assert_array_equal(counts[0.0], counts[2.0])
    np.testing.assert_allclose(logits[0.0], semantic_logits_from_counts(counts[0.0][labelled]).numpy(), rtol=1e-6)
    assert not np.allclose(logits[0.0], logits[2.0])


def test_pixel_ground_length_is_what_one_pixel_spans_along_the_line_of_sight():
    """Checked against the projection itself: two ground points a millimetre apart along the view, how many
    pixels apart they land, for a forward camera 1.5 m up and points 5 to 30 m ahead."""
    camera = CameraModel("front", np.array([[800.0, 0, 400], [0, 800.0, 300], [0, 0, 1]]), (0.0,) * 5, 801, 601)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera z forward along x, y down
    pose[:3, 3] = [0.0, 0.0, 1.5]
    x = np.array([5.0, 10.0, 30.0])
    ground = np.column_stack([x, np.full(3, 0.5), np.zeros(3)])
    along = ground[:, :2] / np.linalg.norm(ground[:, :2], axis=1, keepdims=True)
    step = np.column_stack([along * 0.001, np.zeros(3)])
    uv0, ok0 = project_points(ground, camera, pose)
    uv1, ok1 = project_points(ground + step, camera, pose)
    assert ok0.all() and ok1.all()
    per_pixel = 0.001 / np.linalg.norm(uv1 - uv0, axis=1)
    np.testing.assert_allclose(pixel_ground_length_m(ground, camera, pose), per_pixel, rtol=0.02)
    assert per_pixel[2] > 30 * per_pixel[0]  # why it matters: a far pixel smears a boundary over ~0.5 m


def test_labels_from_sharp_views_outweigh_more_numerous_coarse_ones():
    """One view from 2 m (2 mm pixels) sees lane marking, two from 60 m (6 cm pixels) see road: counted
    equally the road wins; weighted by what a pixel covers (label_sharp_m 2 cm: the far views count 1/3
    each) the sharp view does."""
    mesh = build_road_mesh(HorizontalTrack(np.array([0.0, 10.0]), np.array([[-1.0, 0.0, 1.5], [1.0, 0.0, 1.5]])),
                           0.5, 0.1, 1.5)
    camera = CameraModel("down", np.array([[1000.0, 0, 200], [0, 1000.0, 200], [0, 0, 1]]), (0.0,) * 5, 401, 401)
    points = np.concatenate([mesh.xy, np.zeros((mesh.num_vertices, 1))], 1)
    ids = np.arange(mesh.num_vertices)

    def view(height_m: float, label: SemanticClass) -> Keyframe:
        return Keyframe("down", 0.0, _looking_down(height_m), np.zeros((401, 401, 3), np.uint8),
                        np.full((401, 401), label, np.uint8))

    views = [view(2.0, SemanticClass.LANE_MARKING), view(60.0, SemanticClass.ROAD), view(60.0, SemanticClass.ROAD)]
    winner = {}
    for sharp_m in (None, 0.02):
        obs = VertexObservations.empty(mesh.num_vertices, ["down"])
        for kf in views:
            observe_keyframe(obs, ids, points, kf, camera, label_sharp_m=sharp_m)
        under_all = (np.abs(mesh.xy) < 0.3).all(1)  # the near view spans 0.8 m
        assert under_all.sum() > 20 and (obs.label_counts[under_all].sum(1) > 0).all()
        winner[sharp_m] = set(obs.label_counts[under_all].argmax(1).tolist())
    assert winner == {None: {int(SemanticClass.ROAD)}, 0.02: {int(SemanticClass.LANE_MARKING)}}, winner


def test_lidar_detail_puts_a_curb_step_into_the_smooth_surface():
    """A flat surface under Lidar points of a road with a 15 cm curb: the detail raises the vertices on the
    curb and leaves the road where it is, within a vertex of the step."""
    mesh = build_road_mesh(HorizontalTrack(np.array([0.0, 10.0]), np.array([[0.0, 0.0, 1.5], [20.0, 0.0, 1.5]])),
                           4.0, 0.1, 1.5)
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(0, 20, 100_000), rng.uniform(-4, 4, 100_000)])
    height = np.where(xy[:, 1] > 2.0, 0.15, 0.0) + rng.normal(0.0, 0.005, len(xy))
    z = mesh.z0.copy()
    assert np.abs(z).max() < 1e-6
    detail = fit_lidar_detail(z, Located.of(mesh, xy), height, 8, 0.03, 2)
    assert np.array_equal(z, detail)
    inner = (mesh.xy[:, 0] > 1) & (mesh.xy[:, 0] < 19)
    road = inner & (mesh.xy[:, 1] > -3.8) & (mesh.xy[:, 1] < 1.9)
    curb = inner & (mesh.xy[:, 1] > 2.1) & (mesh.xy[:, 1] < 3.8)
    assert np.abs(z[road]).mean() < 0.005 and np.abs(z[curb] - 0.15).mean() < 0.005
    assert np.abs(z[road]).max() < 0.03 and np.abs(z[curb] - 0.15).max() < 0.03


def test_lidar_detail_fills_the_vertices_between_sparse_points_and_keeps_the_curb_step():
    """Sparse Lidar points (one per ~5 vertices, as in a lane far from the Lidar) of a road 4 cm above the
    smooth surface, with a 15 cm curb: the vertices without a point of their own take their neighbours' detail
    (they kept the smooth surface, 4 cm low, and a label read through them landed centimetres off); the curb
    top, 1.3 m wide and as sparse, comes out within 5 cm on average."""
    mesh = build_road_mesh(HorizontalTrack(np.array([0.0, 10.0]), np.array([[0.0, 0.0, 1.5], [20.0, 0.0, 1.5]])),
                           4.0, 0.1, 1.5)
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(0, 20, 3_000), rng.uniform(-4, 4, 3_000)])
    height = 0.04 + np.where(xy[:, 1] > 2.0, 0.15, 0.0)
    z = mesh.z0.copy()
    fit_lidar_detail(z, Located.of(mesh, xy), height, 8, 0.03, 2, neighbours=mesh.neighbours)
    inner = (mesh.xy[:, 0] > 1) & (mesh.xy[:, 0] < 19)
    road = inner & (mesh.xy[:, 1] > -3.5) & (mesh.xy[:, 1] < 1.8)
    curb = inner & (mesh.xy[:, 1] > 2.2) & (mesh.xy[:, 1] < 3.5)
    assert np.abs(z[road] - 0.04).mean() < 0.01 and np.abs(z[curb] - 0.19).mean() < 0.05  # 2.9 and 13.6 cm before
    assert np.percentile(np.abs(z[road] - 0.04), 90) < 0.02


def _observed_map(scene):
    """An untrained road map over the scene's 5 m corridor (0.2 m mesh), every vertex marked observed."""
    mesh = build_road_mesh(scene.trajectory, 5.0, 0.2, scene.reference_height_m)
    rm = new_road_map(mesh, variant_for(None), sorted(scene.cameras), 32, 2, 16, 22, 8, 128, 40.0, 0.5,
                      torch.Generator().manual_seed(0))
    rm.observed[:] = 1
    return rm


def test_elevation_fit_to_the_lidar_lattice_recovers_the_crossfall(scene):
    torch.set_num_threads(1)  # as the fast path runs it (see mapper.runtime.torch_threads_fast_fit)
    torch.manual_seed(0)
    rm = _observed_map(scene)
    mesh = rm.mesh
    start_cm = elev_mae_gt_cm(rm, scene.gt)
    first, last = fit_elevation(rm, scene.lidar, Located.of(mesh, scene.lidar[:, :2]), 0.5, 5.0, 100, 512, 128, 0.01,
                                1.0, 1.0, np.random.default_rng(0))
    rm.refresh_elevation()
    assert last < 0.5 * first
    assert start_cm > 5.0 and elev_mae_gt_cm(rm, scene.gt) < 0.4 * start_cm


def test_rome_is_camera_only_but_its_elevation_is_still_measured_against_the_lidar(scene):
    cfg = CONFIG
    runs = [reconstruct(scene.keyframes[:24], scene.cameras, scene.trajectory, lidar, cfg, scene.reference_height_m,
                        None, ablation="rome", progress=False) for lidar in (scene.lidar, None)]
    with_points, without = runs
    assert np.array_equal(with_points.road_map.z_now, without.road_map.z_now)  # the points never reached the fit
    assert with_points.metrics["elev_error_cm"] is not None and without.metrics["elev_error_cm"] is None


def test_inputs_still_loading_give_the_same_map_as_loaded_ones(scene):
    cfg = CONFIG
    loaded = reconstruct(scene.keyframes[:24], scene.cameras, scene.trajectory, scene.lidar, cfg,
                         scene.reference_height_m, None, progress=False)
    with ThreadPoolExecutor(1) as pool:  # as mapping.inputs.drive_inputs.LoadingDrive hands them over
        lidar, keyframes = pool.submit(lambda: scene.lidar), pool.submit(lambda: scene.keyframes[:24])
        loading = reconstruct(keyframes, scene.cameras, scene.trajectory, lidar, cfg, scene.reference_height_m,
                              None, progress=False)
    assert np.array_equal(loaded.road_map.z_now, loading.road_map.z_now)
    assert torch.equal(loaded.road_map.colour_params, loading.road_map.colour_params)
    assert loaded.metrics["psnr_db"] == loading.metrics["psnr_db"]
    assert "keyframes_wait_s" in loading.metrics and "keyframes_wait_s" not in loaded.metrics


def test_elev_error_is_the_perpendicular_distance_to_a_sloping_surface(scene):
    rm = _observed_map(scene)
    mesh = rm.mesh
    rm.z_now[:] = 0.3 * mesh.xy[:, 0] - 0.4 * mesh.xy[:, 1]  # a plane: 50 % slope
    rng = np.random.default_rng(0)
    xy = mesh.xy[rng.choice(mesh.num_vertices, 2000)] + rng.uniform(-0.05, 0.05, (2000, 2))
    height = rng.choice([-0.02, 0.02], 2000)  # 2 cm above or below, vertically
    points = np.column_stack([xy, 0.3 * xy[:, 0] - 0.4 * xy[:, 1] + height])
    expected = 2.0 / np.sqrt(1 + 0.3**2 + 0.4**2)  # cm, perpendicular to the plane
    assert elev_error_cm(rm, points) == pytest.approx(expected, rel=1e-3)
    assert elev_error_cm(rm, points, Located.of(mesh, xy)) == pytest.approx(expected, rel=1e-3)


def test_metrics_from_points_located_ahead_of_time_match_the_direct_ones(scene, fast_run):
    road_map = fast_run[0].road_map
    mesh = road_map.mesh  # x, y only: placed before the fit
    points = MetricPoints(Located.of(mesh, scene.lidar[:, :2]), Located.of(mesh, truth_cells(scene.gt)[2]))
    assert elev_error_cm(road_map, scene.lidar, points.lidar) == pytest.approx(elev_error_cm(road_map, scene.lidar),
                                                                               rel=1e-5)
    direct = elev_mae_gt_cm(road_map, scene.gt)
    assert direct is not None and elev_mae_gt_cm(road_map, scene.gt, points.truth) == pytest.approx(direct, rel=1e-5)


def test_a_failing_reconstruction_cancels_its_background_work(scene, monkeypatch):
    rendered = []
    view_seen = map_metrics._view_seen

    def slow_view(*args, **kwargs):
        rendered.append(1)
        time.sleep(0.2)
        return view_seen(*args, **kwargs)

    def broken(*args, **kwargs):
        time.sleep(0.1)  # the evaluation has started its views
        raise RuntimeError("colour fit failed")

    monkeypatch.setattr(map_metrics, "_view_seen", slow_view)
    monkeypatch.setattr(fast_fit, "fit_colour", broken)
    with pytest.raises(RuntimeError, match="colour fit failed"):
        reconstruct(scene.keyframes[:24], scene.cameras, scene.trajectory, scene.lidar,
                    CONFIG, scene.reference_height_m, None, progress=False)
    time.sleep(1.5)  # long enough for every queued view to have rendered, had they not been cancelled
    assert 0 < len(rendered) <= 2 * CONFIG.runtime.evaluation_threads


def test_a_faithful_window_holds_every_vertex_of_its_faces(scene, monkeypatch):
    """A face near a short window's edge has vertices just outside it: each is in the window, so no pixel reads
    another vertex's height, colour code or logits (they once read the window's last vertex and its first row)."""
    outside = []
    losses = FaithfulOptimisation._losses

    def checked(self, sup, ids, touched, lidar_ids, lidar_z, z):
        used = torch.cat([s.tri.reshape(-1) for s in sup] + [touched, lidar_ids])
        outside.append(int((self.lookup[used] < 0).sum()))
        return losses(self, sup, ids, touched, lidar_ids, lidar_z, z)

    monkeypatch.setattr(FaithfulOptimisation, "_losses", checked)
    config = CONFIG.model_copy(update={"faithful_fit": FaithfulFitConfig(epochs=1),
                                       "windows": WindowsConfig(before_m=2.0, after_m=2.0)})
    reconstruct(scene.keyframes, scene.cameras, scene.trajectory, scene.lidar, config, scene.reference_height_m,
                faithful=True, holdout_every=5, progress=False)
    assert len(outside) > 5 and sum(outside) == 0, outside
