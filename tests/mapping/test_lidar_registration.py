"""Lidar ground registration (mapping.fits.lidar_registration): ground points placed with a pose whose height,
roll and pitch wander are registered back onto one surface; exact poses get no correction; bad points are
counted and left out."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from daemon.spine.mapper_config import PoseRefinementConfig
from mapping.fits.lidar_registration import (
    CellPairs,
    cell_eliminated,
    cell_products,
    grouped_normal_matrix,
    knot_groups,
    re_placed,
    register_ground,
    thin_out,
)
from mapping.localization.trajectory import HorizontalTrack

SETTINGS = PoseRefinementConfig(enabled=True)
SPEED = 8.0  # m/s along x
SCAN_HZ = 10.0


def _surface(xy: np.ndarray) -> np.ndarray:
    """A crowned road with a 2 % grade and 15 cm kerbs at |y| > 5 m."""
    return 0.02 * xy[:, 0] - 0.01 * np.abs(xy[:, 1]) + 0.15 * (np.abs(xy[:, 1]) > 5.0)


def _drive(seconds: float, error_cm: float, rng: np.random.Generator):
    """The vehicle's true track, the one it was placed with (a smooth height / roll / pitch error, and some
    along-track and lateral error which the registration must not need), and ground points as that pose placed
    them, with 1 cm of range noise: (track as placed, points, their times, the error's dz and roll/pitch at t)."""
    t = np.arange(0.0, seconds, 0.01)
    true = np.stack([SPEED * t, np.zeros_like(t), 0.02 * SPEED * t + 1.6], 1)
    knots = np.arange(0.0, seconds + 0.5, 0.5)
    draw = rng.standard_normal((len(knots), 6))
    error = np.stack([np.interp(t, knots, draw[:, k]) for k in range(6)], 1)
    error[:, :3] *= error_cm / 100.0 / np.sqrt(3)
    error[:, 3:] *= np.deg2rad(0.1) * (error_cm > 0)
    placed = true + error[:, :3]
    track = HorizontalTrack(t, placed)
    points, times = [], []
    for scan_t in np.arange(0.0, seconds - 0.1, 1 / SCAN_HZ):
        xy = rng.uniform([-25, -12], [25, 12], (3000, 2))
        firing = scan_t + rng.uniform(0, 1 / SCAN_HZ, len(xy))
        i = np.clip(np.searchsorted(t, firing), 0, len(t) - 1)
        ground = np.concatenate([xy + true[i, :2], np.zeros((len(xy), 1))], 1)
        ground[:, 2] = _surface(ground[:, :2]) + rng.normal(0, 0.01, len(xy))
        turned = Rotation.from_rotvec(error[i, 3:]).apply(ground - true[i])
        points.append(placed[i] + turned)
        times.append(firing)
    return track, np.concatenate(points), np.concatenate(times), error


def _height_error_cm(points: np.ndarray) -> float:
    """RMS of the points' height off the true surface, once the plane that fits that best is taken off (the whole
    map's height and tilt are not observable from the ground alone)."""
    off = points[:, 2] - _surface(points[:, :2])
    plane = np.concatenate([np.ones((len(points), 1)), points[:, :2]], 1)
    off = off - plane @ np.linalg.lstsq(plane, off, rcond=None)[0]
    return 100.0 * float(np.sqrt((off ** 2).mean()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_wandering_height_roll_and_pitch_are_registered_onto_one_surface(seed):
    track, points, times, error = _drive(5.0, 20.0, np.random.default_rng(seed))
    timings = {}
    corrections, figures = register_ground(points, times, track, SETTINGS, timings)
    moved = re_placed(points, times, track, corrections)
    before, after = _height_error_cm(points), _height_error_cm(moved)
    assert before > 3.0
    assert after < 0.5 * before and after < 2.0  # the points' own noise is 1 cm
    dz, _ = corrections.at(track.horizontal_distance_at(track.times))
    found = np.corrcoef(dz[:, 2], -error[:, 2])[0, 1]
    assert found > 0.9  # the correction follows the injected height error
    assert np.abs(corrections.position_m[:, :2]).max() == 0 and np.abs(corrections.rotation_rad[:, 2]).max() == 0
    assert figures["residual_rms_cm"][-1] < figures["residual_rms_cm"][0] or figures["residual_rms_cm"][0] < 2.0
    assert figures["knots"] == len(corrections.knots_s) and timings["lidar_registration_wall_s"] > 0


def test_exact_poses_get_no_correction():
    track, points, times, _ = _drive(5.0, 0.0, np.random.default_rng(3))
    corrections, figures = register_ground(points, times, track, SETTINGS, {})
    assert figures["position_max_cm"] < 0.5 and figures["rotation_max_deg"] < 0.01
    assert _height_error_cm(re_placed(points, times, track, corrections)) < 1.2


def test_points_that_are_not_finite_are_counted_and_left_out():
    track, points, times, _ = _drive(3.0, 20.0, np.random.default_rng(4))
    points[::100, 2] = np.nan
    times[1::100] = np.inf
    clean = np.isfinite(points).all(1) & np.isfinite(times)
    corrections, figures = register_ground(points, times, track, SETTINGS, {})
    assert figures["points_skipped"] == int((~clean).sum()) > 0
    assert figures["points"] == int(clean.sum()) and figures["points_thinned"] == 0
    assert np.isfinite(corrections.position_m).all() and np.isfinite(corrections.rotation_rad).all()
    _, figures = register_ground(points, times, track, SETTINGS.model_copy(update={"lidar_max_points": 1000}), {})
    assert figures["points"] == 1000 and figures["points_thinned"] == int(clean.sum()) - 1000


@pytest.mark.parametrize("stride, columns", [(3, [0, 1, 2]), (6, [0, 1, 5]), (6, [0, 1, 2, 3, 4, 5])])
def test_the_normal_matrix_by_knot_groups_is_the_sum_of_every_point_s_outer_product(stride, columns):
    """The registrations' normal matrix, accumulated per group of points between the same two knots, equals the
    plain sum of each point's (weighted derivatives) x (derivatives) placed at its columns."""
    rng = np.random.default_rng(5)
    n, knots = 4000, 12
    k0 = rng.integers(0, knots - 1, n)
    cols = np.concatenate([stride * k0[:, None] + columns, stride * (k0 + 1)[:, None] + columns], 1)
    vals = rng.standard_normal(cols.shape)
    wv = rng.random(n)[:, None] * vals
    m = stride * knots
    expected = np.zeros((m, m))
    for c, w, v in zip(cols, wv, vals, strict=True):
        expected[np.ix_(c, c)] += np.outer(w, v)
    got = grouped_normal_matrix(knot_groups(k0), wv, vals, cols, m)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-9)


def test_the_cell_eliminated_system_is_the_least_squares_of_the_points_about_their_cells_means():
    """With each cell's value a free unknown, the step d minimising sum_p w_p (z_p + vals_p . d[cols_p] - c_cell)^2
    over d and c satisfies (normal) d = rhs; checked against the same least squares written out with the cells'
    values as unknowns beside d and solved densely."""
    rng = np.random.default_rng(8)
    n, knots, stride, columns = 3000, 6, 6, [0, 1, 2, 3, 4, 5]
    k0 = rng.integers(0, knots - 1, n)
    cols = np.concatenate([stride * k0[:, None] + columns, stride * (k0 + 1)[:, None] + columns], 1)
    vals, z = rng.standard_normal(cols.shape), rng.standard_normal(n)
    weight = rng.random(n) * (rng.random(n) > 0.1)  # some points without weight
    cell = rng.integers(0, 200, n)
    m = stride * knots
    normal, rhs, residual = cell_eliminated(cell, weight, vals, cols, z, m, knot_groups(k0),
                                            CellPairs.of(cell, cols[:, 0], m))
    design = np.zeros((n, m + 200))  # unknowns: d, then each cell's value
    np.add.at(design, (np.arange(n)[:, None], cols), vals)
    design[np.arange(n), m + cell] = -1.0
    full = design.T @ (weight[:, None] * design)
    full_rhs = -design.T @ (weight * z)
    seen = np.flatnonzero(np.bincount(cell, weight, 200) > 0)  # a cell without weight has no value to solve for
    keep = np.concatenate([np.arange(m), m + seen])
    full, full_rhs = full[np.ix_(keep, keep)], full_rhs[keep]
    eliminated = full[:m, :m] - full[:m, m:] @ np.linalg.solve(full[m:, m:], full[m:, :m])
    np.testing.assert_allclose(normal, eliminated, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(rhs, full_rhs[:m] - full[:m, m:] @ np.linalg.solve(full[m:, m:], full_rhs[m:]),
                               rtol=1e-9, atol=1e-9)
    means = np.bincount(cell, weight * z, 200) / np.maximum(np.bincount(cell, weight, 200), 1e-12)
    np.testing.assert_allclose(residual, z - means[cell])


@pytest.mark.parametrize("chunk, max_span", [(2048, 512), (7, 13), (1, 1)])
def test_the_cells_products_by_dense_bands_and_by_the_sparse_product_are_the_sum_of_each_cells(chunk, max_span):
    """sum_c s_c b_c b_c^T, by chunks of cells in dense bands of columns, and for cells spanning more than
    max_span columns by the sparse product (a road seen twice far apart), equals each cell's outer product summed."""
    rng = np.random.default_rng(3)
    cells, m = 60, 48
    row_cell = np.sort(rng.integers(0, cells, 400))
    row_cell[:cells] = np.arange(cells)  # every cell has rows
    row_cell.sort()
    k0 = rng.integers(0, 7, len(row_cell))
    k0[row_cell % 5 == 0] += rng.integers(0, 2, (row_cell % 5 == 0).sum()) * 7  # some cells seen far apart
    row_cols = np.concatenate([3 * k0[:, None] + np.arange(3), 3 * (k0 + 1)[:, None] + np.arange(3)], 1)
    key = row_cell * m + row_cols[:, 0]
    order = np.argsort(key, kind="stable")
    row_cell, row_cols = row_cell[order], row_cols[order]
    row_vals, scale = rng.standard_normal(row_cols.shape), rng.random(cells)
    expected = np.zeros((m, m))
    for c in range(cells):
        b = np.zeros(m)
        np.add.at(b, row_cols[row_cell == c], row_vals[row_cell == c])
        expected += scale[c] * np.outer(b, b)
    got = cell_products(row_cell, row_cols, row_vals, scale, m, chunk=chunk, max_span=max_span)
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10)


def test_thinning_keeps_an_even_subsample_of_the_good_points():
    good = np.ones(10_000, bool)
    good[::10] = False  # 9,000 good
    assert thin_out(good, 3_000) == 6_000
    assert good.sum() == 3_000 and not good[::10].any()
    halves = good.reshape(2, -1).sum(1)
    assert abs(halves[0] - halves[1]) < 200  # spread over all of them, not the first 3,000
    kept = good.copy()
    assert thin_out(good, 5_000) == 0
    assert (good == kept).all()  # at or below the cap: nothing dropped
