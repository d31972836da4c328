"""Lidar ground registration (the pose refinement's first stage when the Lidar ground is given,
`mapper.pose_refinement.lidar_registration`): the height, roll and pitch of the vehicle's pose corrected along the
track so that the ground points of every moment agree with the others' on the same patch of road.

Each ground point was placed with the pose at its firing time. A correction (dz, droll, dpitch) at the knots of
the photometric corrections (mapping.fits.pose_refinement: `knot_spacing_m` apart, linear between), applied on the
left about the vehicle's reference point, moves the point's height by dz + wx * ry - wy * rx (small angles; r the
point's offset from the reference point at its time). The points are binned into `lidar_cell_m` cells; the fit
minimises the squared difference of each point's corrected height from its cell's height (one unknown per cell,
eliminated in closed form: the normal equations are 3 per knot), each over `lidar_point_sigma_m`, plus the prior
towards zero (`prior_m`, `prior_deg`: the whole map's height and tilt are not observable from the Lidar alone) and
the smoothness between knots (`smooth_m`, `smooth_deg`). `lidar_rounds` rounds reweight each point (Huber at
`lidar_huber_m`) so that kerbs' edges and what stands on the road count less. A cell seen at one moment only
constrains nothing. x, y and yaw are left to the photometric fit, which then holds these three axes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from daemon.spine.mapper_config import PoseRefinementConfig
from mapping.fits.pose_refinement import PoseCorrections, knot_positions, reference_points
from mapping.localization.trajectory import HorizontalTrack

GAUGE_WEIGHT = 1e12  # against the data's normal matrix (~1e9 per unit of correction): held at zero


def register_ground(points: np.ndarray, seconds: np.ndarray, trajectory: HorizontalTrack,
                    settings: PoseRefinementConfig, timings: dict[str, float]) -> tuple[PoseCorrections, dict]:
    """The corrections (dz, roll, pitch; x, y, yaw zero) that make the ground points (N, 3), fired at `seconds`
    from the track's start, agree (module docstring); figures for the metrics (`lidar_registration`). Points or
    times that are not finite are left out and counted (`points_skipped`)."""
    started = time.perf_counter()
    knot_s = knot_positions(trajectory, settings.knot_spacing_m)
    good = np.isfinite(points).all(1) & np.isfinite(seconds)
    skipped = int((~good).sum())  # not finite: counted in the figures, left out
    thinned = thin_out(good, settings.lidar_max_points)
    pts, t = points[good], seconds[good]
    s = trajectory.horizontal_distance_at(t)
    r = pts - reference_points(trajectory, t)
    # per point: its knots and weights, and its height's derivative by (dz, wx, wy) of each knot
    k0 = np.clip(np.searchsorted(knot_s, s, side="right") - 1, 0, len(knot_s) - 2)
    frac = np.clip((s - knot_s[k0]) / (knot_s[k0 + 1] - knot_s[k0]), 0.0, 1.0)
    local = np.stack([np.ones(len(s)), r[:, 1], -r[:, 0]], 1)  # (N, 3)
    cols = np.concatenate([3 * k0[:, None] + np.arange(3), 3 * (k0 + 1)[:, None] + np.arange(3)], 1)  # (N, 6)
    vals = np.concatenate([local * (1 - frac)[:, None], local * frac[:, None]], 1)  # (N, 6)
    m = 3 * len(knot_s)
    cell_xy = np.floor(pts[:, :2] / settings.lidar_cell_m).astype(np.int64)
    _, cell = np.unique(cell_xy[:, 0] * 2_000_003 + cell_xy[:, 1], return_inverse=True)
    cell = cell.ravel()
    cells = int(cell.max()) + 1
    scale = np.tile([settings.prior_m, np.deg2rad(settings.prior_deg), np.deg2rad(settings.prior_deg)], len(knot_s))
    step = np.tile([settings.smooth_m, np.deg2rad(settings.smooth_deg), np.deg2rad(settings.smooth_deg)],
                   len(knot_s) - 1)
    D = sp.diags([-np.ones(m - 3), np.ones(m - 3)], [0, 3], shape=(m - 3, m))
    fixed = np.diag(1.0 / scale ** 2) + (D.T @ sp.diags(1.0 / step ** 2) @ D).toarray() \
        + _gauge_penalty(trajectory, knot_s, scale)  # prior, smoothness, gauge
    groups, pairs = knot_groups(k0), CellPairs.of(cell, cols[:, 0], m)
    z = pts[:, 2]
    theta = np.zeros(m)
    weight = np.ones(len(s))
    sigma2 = settings.lidar_point_sigma_m ** 2
    spread = []
    for _ in range(settings.lidar_rounds):
        normal, rhs, _ = cell_eliminated(cell, weight, vals, cols, z, m, groups, pairs)
        theta = np.linalg.solve(normal / sigma2 + fixed, rhs / sigma2)
        cell_w = np.maximum(np.bincount(cell, weight, cells), 1e-12)
        moved = z + (vals * theta[cols]).sum(1)
        residual = moved - (np.bincount(cell, weight * moved, cells) / cell_w)[cell]
        spread.append(float(np.sqrt(np.average(residual ** 2, weights=weight))))
        weight = np.minimum(1.0, settings.lidar_huber_m / np.maximum(np.abs(residual), 1e-9))
    knots = theta.reshape(-1, 3)
    position = np.zeros((len(knot_s), 3))
    rotation = np.zeros((len(knot_s), 3))
    position[:, 2], rotation[:, :2] = knots[:, 0], knots[:, 1:]
    corrections = PoseCorrections(knot_s, position, rotation)
    timings["lidar_registration_wall_s"] = time.perf_counter() - started
    return corrections, {"points": len(s), "points_skipped": skipped, "points_thinned": thinned, "cells": cells,
                         "residual_rms_cm": [100.0 * v for v in spread], **corrections.figures()}


@dataclass(frozen=True)
class CellPairs:
    """The points grouped by (cell, knot pair): the points of one cell between the same two knots share their
    columns, so the cells' sums are taken over these groups, not over every point."""

    of_point: np.ndarray  # (N,) each point's group
    cell: np.ndarray  # (G,) each group's cell, in order (np.unique's), then by first column
    point: np.ndarray  # (G,) a point of each group (its columns are the group's)

    @staticmethod
    def of(cell: np.ndarray, first_col: np.ndarray, m: int) -> CellPairs:
        pair, inverse = np.unique(cell.astype(np.int64) * m + first_col, return_inverse=True)
        inverse = inverse.ravel()
        point = np.empty(len(pair), np.int64)
        point[inverse] = np.arange(len(cell))
        return CellPairs(inverse, pair // m, point)


def cell_eliminated(cell: np.ndarray, weight: np.ndarray, vals: np.ndarray, cols: np.ndarray, z: np.ndarray,
                     m: int, groups: list[np.ndarray],
                     pairs: CellPairs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normal matrix (m, m) and right-hand side (m,) of a step d of the knots that minimises the weighted squares
    of z + vals . d[cols] less its cell's mean (each cell's value a free unknown, eliminated in closed form); and
    each point's residual at d = 0. Points with the same first column have the same columns (those of their knot
    pair, as in `groups`); `pairs` is CellPairs.of(cell, cols[:, 0], m)."""
    cells = int(cell.max()) + 1
    cell_w = np.maximum(np.bincount(cell, weight, cells), 1e-12)
    wv = weight[:, None] * vals
    AtWA = grouped_normal_matrix(groups, wv, vals, cols, m)
    # B (cells, m): each cell's sum of its points' weighted derivatives, one row of q entries per (cell, knot pair)
    summed = np.stack([np.bincount(pairs.of_point, wv[:, j], len(pairs.cell)) for j in range(cols.shape[1])], 1)
    BtB = cell_products(pairs.cell, cols[pairs.point], summed, 1.0 / cell_w, m)
    residual = z - (np.bincount(cell, weight * z, cells) / cell_w)[cell]
    # A^T W z - B^T (the cells' means), summed as A^T W (z less its cell's mean): the same, without the cancellation
    # of two large sums (which left relative errors of 1e-10 that the gauge-held solve amplified)
    rhs = -np.bincount(cols.ravel(), (wv * residual[:, None]).ravel(), m)
    return AtWA - BtB, rhs, residual


def cell_products(row_cell: np.ndarray, row_cols: np.ndarray, row_vals: np.ndarray, cell_scale: np.ndarray, m: int,
                  chunk: int = 2048, max_span: int = 512) -> np.ndarray:
    """sum over cells c of cell_scale[c] b_c b_c^T (m, m), where b_c (m,) sums the rows (values `row_vals` (R, q) at
    columns `row_cols` (R, q)) of cell c; the rows sorted by cell and within a cell by first column (as np.unique
    gives them), every cell with rows. A cell's columns lie between its first and last knots: the cells, in order of
    their first column, are taken up to `chunk` at a time as dense (cells, band) blocks multiplied by BLAS (a scipy
    sparse product took ten times longer); cells whose columns span more than `max_span` (a road seen again much
    later) go through the sparse product."""
    cells = len(cell_scale)  # each has rows
    lo = row_cols.min(1)[np.searchsorted(row_cell, np.arange(cells))]
    hi = row_cols.max(1)[np.searchsorted(row_cell, np.arange(cells), side="right") - 1] + 1
    wide = hi - lo > max_span
    order = np.flatnonzero(~wide)
    order = order[np.argsort(lo[order], kind="stable")]
    rank = np.full(cells, len(order))
    rank[order] = np.arange(len(order))
    row_rank = rank[row_cell]
    row_order = np.argsort(row_rank, kind="stable")
    sorted_rank, sorted_lo = row_rank[row_order], lo[order]
    out = np.zeros((m, m))
    q = row_cols.shape[1]
    start = 0
    while start < len(order):  # a chunk's first columns within max_span of each other: its band < 2 max_span
        end = min(start + chunk, int(np.searchsorted(sorted_lo, sorted_lo[start] + max_span, side="right")))
        here = order[start:end]
        b_lo, b_hi = int(lo[here].min()), int(hi[here].max())
        rows = row_order[np.searchsorted(sorted_rank, start):np.searchsorted(sorted_rank, end)]
        flat = ((row_rank[rows] - start)[:, None] * (b_hi - b_lo) + (row_cols[rows] - b_lo)).ravel()
        dense = np.bincount(flat, row_vals[rows].ravel(), len(here) * (b_hi - b_lo)).reshape(len(here), -1)
        out[b_lo:b_hi, b_lo:b_hi] += dense.T @ (dense * cell_scale[here][:, None])
        start = end
    rows = np.flatnonzero(wide[row_cell])
    if len(rows):
        B = sp.csr_matrix((row_vals[rows].ravel(), (np.repeat(row_cell[rows], q), row_cols[rows].ravel())),
                          shape=(cells, m))
        out += (B.T @ sp.diags(cell_scale) @ B).toarray()
    return out


def thin_out(good: np.ndarray, max_points: int) -> int:
    """Keep at most `max_points` of the `good` points, an even random subsample (in place; seeded); how many were
    dropped."""
    n = int(good.sum())
    if n > max_points:
        good[np.flatnonzero(good)[np.random.default_rng(0).permutation(n)[max_points:]]] = False
    return max(0, n - max_points)


def knot_groups(k0: np.ndarray) -> list[np.ndarray]:
    """The points' indices grouped by their first knot `k0` (each group's points have the same columns)."""
    order = np.argsort(k0, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(k0[order])) + 1)


def grouped_normal_matrix(groups: list[np.ndarray], wv: np.ndarray, vals: np.ndarray, cols: np.ndarray,
                          m: int) -> np.ndarray:
    """The sum over the points of wv_p^T vals_p (the rows (N, q) of weighted and plain derivatives by the knots at
    columns `cols` (N, q)) as an (m, m) matrix: one q x q product per knot group, so the memory stays that of the
    points (an (N, q, q) outer product would hold 36-144 floats a point)."""
    out = np.zeros((m, m))
    for idx in groups:
        if len(idx):
            c = cols[idx[0]]
            out[np.ix_(c, c)] += wv[idx].T @ vals[idx]
    return out


def _gauge_penalty(trajectory: HorizontalTrack, knot_s: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """A penalty (3K, 3K) that keeps the corrections free of what the ground cannot tell: a change of the whole
    map's height, or a tilt of the whole map (a correction dz = a + b X + c Y at each knot with roll c, pitch -b
    moves every point by a + b X + c Y, whatever the moment that saw it). The corrections are kept orthogonal to
    these three, in the prior's metric (the smallest correction the ground allows)."""
    seconds = np.interp(knot_s, trajectory.horizontal_distance(), trajectory.times)
    xy = reference_points(trajectory, seconds)[:, :2]
    xy = xy - xy.mean(0)
    modes = np.zeros((3, len(knot_s), 3))
    modes[0, :, 0] = 1.0
    modes[1, :, 0], modes[1, :, 2] = xy[:, 0], -1.0
    modes[2, :, 0], modes[2, :, 1] = xy[:, 1], 1.0
    g = modes.reshape(3, -1) / scale ** 2  # prior-metric directions
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return GAUGE_WEIGHT * g.T @ g


def re_placed(points: np.ndarray, seconds: np.ndarray, trajectory: HorizontalTrack,
              corrections: PoseCorrections) -> np.ndarray:
    """The ground points moved by the corrections at their firing times (as the vehicle's pose is)."""
    position, rotation = corrections.at(trajectory.horizontal_distance_at(seconds))
    reference = reference_points(trajectory, seconds)
    # rotation vectors of a few degrees at most: first order plus the second-order term (Rodrigues)
    theta = np.linalg.norm(rotation, axis=1, keepdims=True)
    offset = points - reference
    cross = np.cross(rotation, offset)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(theta > 0, np.sin(theta) / theta, 1.0)
        b = np.where(theta > 0, (1 - np.cos(theta)) / theta ** 2, 0.5)
    turned = offset + a * cross + b * np.cross(rotation, cross)
    return reference + position + turned
