"""Lidar horizontal registration (the pose refinement's second Lidar stage, `mapper.pose_refinement
.lidar_horizontal`): the x, y and yaw of the vehicle's pose corrected along the track so that what the ground
points of every moment saw on the road (lane paint, which is retroreflective, patches, stains: the points' intensity
contrast, mapping.inputs.lidar_ground.intensity_contrast; and the kerbs' and the crown's slopes: their heights)
lies where the other moments saw it.

The corrections are (dx, dy, dyaw) at the knots of the photometric corrections (mapping.fits.pose_refinement:
`knot_spacing_m` apart, linear between), applied on the left about the vehicle's reference point: a point moves by
(dx - dyaw * ry, dy + dyaw * rx), r its offset from the reference point at its firing time. The fit is Gauss-Newton
against the map the points make themselves: in rounds, coarse to fine (`lidar_horizontal_blur_m`), the points
(as the corrections so far place them) are rasterised into a contrast field and a height field, each the
Gaussian-weighted mean of the points around (the blur's sigma); every point's contrast and height residual against
the fields at its place and the fields' gradients there give one linear least-squares step for the knots (the
residuals over `lidar_contrast_sigma` and `lidar_point_sigma_m`, Huber-reweighted), with the prior towards zero, the
smoothness between knots and a gauge (the whole map's position and heading are not observable from the Lidar
alone: the corrections are kept free of a common shift and turn). A cell is seen by every scan within the Lidar's
range, so a point's own pull on the field is small; points without a contrast (a Lidar without intensity) count by
their heights only. The height registration (mapping.fits.lidar_registration) runs first and holds height, roll and
pitch.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import gaussian_filter, map_coordinates

from daemon.spine.mapper_config import PoseRefinementConfig
from mapping.fits.lidar_registration import (
    GAUGE_WEIGHT,
    CellPairs,
    cell_eliminated,
    knot_groups,
    re_placed,
    thin_out,
)
from mapping.fits.pose_refinement import PoseCorrections, knot_positions, reference_points
from mapping.localization.trajectory import HorizontalTrack

MAX_RASTER_CELLS = 40_000_000  # the fields' rasters are coarsened beyond this many cells (memory)


def register_horizontal(points: np.ndarray, seconds: np.ndarray, contrast: np.ndarray | None,
                        trajectory: HorizontalTrack, settings: PoseRefinementConfig, timings: dict[str, float],
                        start: PoseCorrections | None = None) -> tuple[PoseCorrections, dict]:
    """The corrections that make the ground points (N, 3), fired at `seconds` from the track's start, with intensity
    contrasts `contrast` (N,) (NaN or None: none), agree horizontally as well as in height (module docstring),
    from `start` (the height registration's, mapping.fits.lidar_registration; None: zero): all six axes are fitted
    together (on a grade an along-track shift and a height change look alike to the heights alone); figures for
    the metrics (`lidar_horizontal_registration`)."""
    started = time.perf_counter()
    knot_s = knot_positions(trajectory, settings.knot_spacing_m)
    if contrast is None:
        contrast = np.full(len(points), np.nan)
    good = np.isfinite(points).all(1) & np.isfinite(seconds)
    skipped = int((~good).sum())
    thinned = thin_out(good, settings.lidar_max_points)
    pts, t, c = points[good], seconds[good], np.asarray(contrast, np.float64)[good]
    has_c = np.isfinite(c)
    s = trajectory.horizontal_distance_at(t)
    r = pts - reference_points(trajectory, t)
    k0 = np.clip(np.searchsorted(knot_s, s, side="right") - 1, 0, len(knot_s) - 2)
    frac = np.clip((s - knot_s[k0]) / (knot_s[k0 + 1] - knot_s[k0]), 0.0, 1.0)
    m = 6 * len(knot_s)  # per knot (dx, dy, dz, droll, dpitch, dyaw): PoseCorrections' position, rotation
    horizontal, everything = np.array([0, 1, 5]), np.arange(6)
    cols_h = np.concatenate([6 * k0[:, None] + horizontal, 6 * (k0 + 1)[:, None] + horizontal], 1)  # (N, 6)
    cols_all = np.concatenate([6 * k0[:, None] + everything, 6 * (k0 + 1)[:, None] + everything], 1)  # (N, 12)
    groups = knot_groups(k0)
    angle = np.deg2rad(settings.prior_deg)
    scale = np.tile([settings.prior_m] * 3 + [angle] * 3, len(knot_s))
    step = np.tile([settings.smooth_m] * 3 + [np.deg2rad(settings.smooth_deg)] * 3, len(knot_s) - 1)
    D = sp.diags([-np.ones(m - 6), np.ones(m - 6)], [0, 6], shape=(m - 6, m))
    fixed = np.diag(1.0 / scale ** 2) + (D.T @ sp.diags(1.0 / step ** 2) @ D).toarray() \
        + _gauge_penalty(trajectory, knot_s, scale)
    theta = np.zeros(m) if start is None else np.concatenate([start.position_m, start.rotation_rad], 1).ravel()
    weights = {"contrast": np.ones(len(c)), "height": np.ones(len(c))}  # Huber, from the round before
    rounds = []
    for blur in settings.lidar_horizontal_blur_m:
        for _ in range(settings.lidar_horizontal_rounds):
            moved = re_placed(pts, t, trajectory, _as_corrections(knot_s, theta))
            field = _Fields.of(moved, c, has_c, blur)
            normal, rhs, spread = np.zeros((m, m)), np.zeros(m), {}
            cell_m = max(blur / 2.0, settings.lidar_horizontal_min_cell_m)
            cell_xy = np.floor(moved[:, :2] / cell_m).astype(np.int64)
            _, cell = np.unique(cell_xy[:, 0] * 2_000_003 + cell_xy[:, 1], return_inverse=True)
            cell = cell.ravel()
            pairs = CellPairs.of(cell, cols_all[:, 0], m)  # the same for both fields (cols_h[:, 0] is cols_all[:, 0])
            for name, value, sigma, usable in (
                    ("contrast", c, settings.lidar_contrast_sigma, has_c),
                    ("height", moved[:, 2], settings.lidar_point_sigma_m, np.ones(len(c), bool))):
                _, gx, gy, seen = field.sample(name, moved[:, :2])
                use = usable & seen
                # the point's value as its cell would hold it once the point moves by the correction: its own value
                # (its height moved by dz + droll * ry - dpitch * rx) less the field's gradient along its horizontal
                # move (dx - dyaw * ry, dy + dyaw * rx); the cell's value is a free unknown (eliminated)
                along_move = -np.stack([gx, gy, -gx * r[:, 1] + gy * r[:, 0]], 1)
                if name == "height":
                    local = np.stack([along_move[:, 0], along_move[:, 1], np.ones(len(r)), r[:, 1], -r[:, 0],
                                      along_move[:, 2]], 1) / sigma
                    cols = cols_all
                else:
                    local, cols = along_move / sigma, cols_h
                vals = np.concatenate([local * (1 - frac)[:, None], local * frac[:, None]], 1)
                z = np.where(use, value, 0.0) / sigma
                weight = use * weights[name]
                n, g, res = cell_eliminated(cell, weight, vals, cols, z, m, groups, pairs)
                normal += n
                rhs += g
                spread[name] = sigma * float(np.sqrt(np.average(res ** 2, weights=np.maximum(weight, 1e-12))))
                weights[name] = np.minimum(1.0, settings.lidar_horizontal_huber / np.maximum(np.abs(res), 1e-9))
            # one Gauss-Newton step about theta: the prior and the smoothness act on the whole correction
            theta = theta + np.linalg.solve(normal + fixed, rhs - fixed @ theta)
            rounds.append({"blur_m": blur, "contrast_rms": spread["contrast"],
                           "height_rms_cm": 100.0 * spread["height"]})
    corrections = _as_corrections(knot_s, theta)
    timings["lidar_horizontal_registration_wall_s"] = time.perf_counter() - started
    return corrections, {"points": len(s), "points_skipped": skipped, "points_thinned": thinned,
                         "points_with_contrast": int(has_c.sum()), "rounds": rounds, **corrections.figures()}


def _as_corrections(knot_s: np.ndarray, theta: np.ndarray) -> PoseCorrections:
    knots = theta.reshape(-1, 6)
    return PoseCorrections(knot_s, knots[:, :3].copy(), knots[:, 3:].copy())


class _Fields:
    """The points' contrast and height as fields over the ground plane: Gaussian-weighted means on a raster."""

    def __init__(self, origin: np.ndarray, cell: float, fields: dict[str, np.ndarray],
                 seen: dict[str, np.ndarray]) -> None:
        self.origin, self.cell, self.fields, self.seen = origin, cell, fields, seen
        self.gradients = {name: np.gradient(f, cell) for name, f in fields.items()}  # (d/drow = y, d/dcol = x)

    @staticmethod
    def of(points: np.ndarray, contrast: np.ndarray, has_contrast: np.ndarray, blur_m: float) -> _Fields:
        cell = max(blur_m / 2.0, 0.02)
        lo = points[:, :2].min(0) - 4 * blur_m
        span = points[:, :2].max(0) + 4 * blur_m - lo
        while np.prod(np.ceil(span / cell) + 1) > MAX_RASTER_CELLS:
            cell *= 1.5
        shape = tuple(int(v) for v in (np.ceil(span[::-1] / cell) + 1))  # (rows: y, cols: x)
        ij = np.floor((points[:, :2] - lo) / cell + 0.5).astype(np.int64)
        flat = ij[:, 1] * shape[1] + ij[:, 0]
        size = shape[0] * shape[1]
        sigma = blur_m / cell

        def smoothed(values: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            total = gaussian_filter(np.bincount(flat[where], values[where], size).reshape(shape), sigma)
            count = gaussian_filter(np.bincount(flat[where], None, size).astype(np.float64).reshape(shape), sigma)
            return total, count

        everywhere = np.ones(len(points), bool)
        z_total, z_count = smoothed(points[:, 2], everywhere)
        c_total, c_count = smoothed(np.nan_to_num(contrast), has_contrast)
        floor = 2.0 / (2 * np.pi * max(sigma, 0.5) ** 2)  # about two points' weight at their centre
        seen = {"height": z_count > floor, "contrast": c_count > floor}
        fields = {"height": np.where(seen["height"], z_total / np.maximum(z_count, 1e-12), 0.0),
                  "contrast": np.where(seen["contrast"], c_total / np.maximum(c_count, 1e-12), 0.0)}
        return _Fields(lo, cell, fields, seen)

    def sample(self, name: str, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The field, its x and y gradients at `xy` (bilinear) and whether the raster holds enough points there."""
        at = ((xy - self.origin) / self.cell)[:, ::-1].T  # (row, col)
        value = map_coordinates(self.fields[name], at, order=1, mode="nearest")
        gy = map_coordinates(self.gradients[name][0], at, order=1, mode="nearest")
        gx = map_coordinates(self.gradients[name][1], at, order=1, mode="nearest")
        seen = map_coordinates(self.seen[name].astype(np.float32), at, order=0, mode="nearest") > 0.5
        return value, gx, gy, seen


def _gauge_penalty(trajectory: HorizontalTrack, knot_s: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """A penalty (6K, 6K) that keeps the corrections free of what the Lidar cannot tell, in the prior's metric: a
    shift of the whole map in x, y or height, a turn of the whole map about the track's middle (dyaw = a at each
    knot with dx = -a (Y - Ym), dy = a (X - Xm)), and a tilt of the whole map (dz = b X with dpitch = -b, dz = b Y
    with droll = b; as mapping.fits.lidar_registration)."""
    seconds = np.interp(knot_s, trajectory.horizontal_distance(), trajectory.times)
    xy = reference_points(trajectory, seconds)[:, :2]
    xy = xy - xy.mean(0)
    modes = np.zeros((6, len(knot_s), 6))
    modes[0, :, 0] = 1.0
    modes[1, :, 1] = 1.0
    modes[2, :, 2] = 1.0
    modes[3, :, 0], modes[3, :, 1], modes[3, :, 5] = -xy[:, 1], xy[:, 0], 1.0
    modes[4, :, 2], modes[4, :, 4] = xy[:, 0], -1.0
    modes[5, :, 2], modes[5, :, 3] = xy[:, 1], 1.0
    g = modes.reshape(6, -1) / scale ** 2
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return GAUGE_WEIGHT * g.T @ g
