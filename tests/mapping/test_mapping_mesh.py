import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapping.localization.trajectory import HorizontalTrack
from mapping.method.road_mesh import build_road_mesh, locate, node_xy, used_vertices


@pytest.fixture(scope="module")
def curve():
    t = np.linspace(0, 10, 101)
    pos = np.stack([4 * t, 6 * np.sin(t / 3), 0.3 * t], 1)
    return HorizontalTrack(t, pos), build_road_mesh(HorizontalTrack(t, pos), 5.0, 0.2, 0.5)


def test_faces_are_equilateral_and_counter_clockwise(curve):
    _, mesh = curve
    v = mesh.xy[mesh.faces]
    sides = np.linalg.norm(v[:, [1, 2, 0]] - v, axis=2)
    assert np.allclose(sides, 0.2, atol=1e-9)
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    assert (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0).all()


def test_mesh_covers_the_corridor_and_nothing_beyond(curve):
    traj, mesh = curve
    dense = np.stack([np.interp(np.linspace(0, 10, 5000), traj.times, traj.positions[:, k]) for k in range(2)], 1)
    d_vertex = cKDTree(dense).query(mesh.xy)[0]
    assert d_vertex.max() <= 5.0 + 0.05
    rng = np.random.default_rng(1)
    k = rng.integers(0, len(dense), 4000)
    normal = np.gradient(dense, axis=0)[k][:, ::-1] * [1, -1]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    inside = dense[k] + normal * rng.uniform(-4.7, 4.7, (len(k), 1))
    _, _, ok = locate(mesh, inside)
    assert ok.all()
    rows, cols = mesh.node_index.shape  # every lattice node within the corridor is a vertex
    rc = np.stack(np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij"), -1).reshape(-1, 2)
    d_node = cKDTree(dense).query(node_xy(rc, mesh.origin, mesh.side_m))[0]
    assert (mesh.node_index.reshape(-1)[d_node < 5.0 - 0.05] >= 0).all()


@pytest.mark.parametrize("length_m", np.linspace(10.0, 11.0, 41))
def test_the_lattice_past_the_corridor_bounds_is_left_out_whatever_the_drive_length(length_m):
    """The lattice reaches past the bounding box the corridor test divides into squares (a 10.725 m drive
    once indexed a square beyond the last)."""
    track = HorizontalTrack(np.array([0.0, 10.0]), np.array([[0.0, 0.0, 1.5], [length_m, 0.0, 1.5]]))
    mesh = build_road_mesh(track, 2.0, 0.1, 1.5)
    x, y = mesh.xy[:, 0], mesh.xy[:, 1]
    d = np.hypot(np.maximum(0.0, np.maximum(-x, x - length_m)), y)
    assert d.max() <= 2.0 + 1e-9 and mesh.num_vertices > 0.9 * (length_m + np.pi) * 4.0 / (0.1 * 0.1 * np.sqrt(3) / 2)


def test_locate_interpolates_points_exactly(curve):
    _, mesh = curve
    rng = np.random.default_rng(2)
    p = mesh.xy[rng.integers(0, mesh.num_vertices, 5000)] + rng.normal(0, 0.1, (5000, 2))
    ids, w, ok = locate(mesh, p)
    assert ok.mean() > 0.9
    assert w[ok].min() > -1e-9
    assert np.allclose((mesh.xy[ids[ok]] * w[ok, :, None]).sum(1), p[ok], atol=1e-9)


def test_neighbours_are_one_side_apart_and_z0_follows_the_trajectory(curve):
    traj, mesh = curve
    nb = mesh.neighbours
    i, j = np.nonzero(nb >= 0)
    assert np.allclose(np.linalg.norm(mesh.xy[i] - mesh.xy[nb[i, j]], axis=1), 0.2)
    assert (nb >= 0).sum(1).max() == 6
    # z0 = trajectory height at the vertex's along-track position minus the reference height
    s_traj = traj.horizontal_distance()
    assert np.allclose(mesh.z0, np.interp(mesh.s, s_traj, traj.positions[:, 2]) - 0.5, atol=1e-5)
    flat = build_road_mesh(traj, 5.0, 0.2, 0.5, flat=True)
    assert np.ptp(flat.z0) == 0


def test_used_vertices_is_a_linear_time_unique_with_inverse():
    ids = np.random.default_rng(3).integers(0, 1000, (700, 3))
    used, local = used_vertices(ids, 1000)
    expected, inverse = np.unique(ids, return_inverse=True)
    assert np.array_equal(used, expected) and np.array_equal(local, inverse.reshape(ids.shape))
    assert np.array_equal(used[local], ids)
