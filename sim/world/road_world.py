"""The simulated road's geometry and its ground truth.

A smooth centre line (curvature profile) with an elevation profile (grade profile: slopes, crests,
sags), a crowned cross-section with raised curbs, sidewalks and verges, and a painted surface (the
atlas, sim/world/road_atlas.py) in road coordinates (s along the centre line, t to its left). World
coordinates are the local ENU frame of the scenario's origin. This module owns the lookups from ENU
(x, y) to road coordinates, surface height and paint, and the ground-truth grids sampled from them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.interpolate import PchipInterpolator

from daemon.spine.semantic_classes import SemanticClass
from sim.world.road_atlas import HALF_WIDTH_M, RoadAtlas, paint_atlas
from sim.world.scenarios import ProfilePoint, RoadSpec, Scenario

CENTRELINE_STEP_M = 0.25
CROSS_STEP_M = 0.01
LOOKUP_RES_M = 0.25
CURB_FACE_M = 0.02  # horizontal width of the curb's (nearly vertical) face
SIDEWALK_FALL = 0.015  # sidewalks drain towards the road
VERGE_RISE = 0.03
GT_RES_M = 0.05
GT_HALF_WIDTH_M = 20.0
NO_CLASS = 255  # ground-truth semantic value outside the mapped corridor


@dataclass
class Centreline:
    """The centre line sampled every CENTRELINE_STEP_M of horizontal arc length s."""

    s: np.ndarray  # (N,) float64
    xy: np.ndarray  # (N, 2) ENU east/north
    heading: np.ndarray  # (N,) radians, counter-clockwise from east
    z: np.ndarray  # (N,) height of the crown (centre line) above the origin
    grade: np.ndarray  # (N,) dz/ds
    tangent: np.ndarray  # (N, 2) unit tangent (east, north)


@dataclass
class CrossSection:
    """Surface height relative to the crown as a function of t, sampled every CROSS_STEP_M."""

    t0: float
    height: np.ndarray  # (M,) float32
    slope: np.ndarray  # (M,) float32, dh/dt


@dataclass
class RoadWorld:
    scenario: Scenario
    centreline: Centreline
    cross: CrossSection
    lookup_origin: tuple[float, float]  # ENU (x, y) of lookup node (0, 0)
    lookup_st: np.ndarray  # (rows along y, columns along x, 2) float32 road coordinates (s, t) of each node
    atlas: RoadAtlas
    height: np.ndarray  # (atlas rows, atlas columns) float32 surface height at each texel centre

    @property
    def length_m(self) -> float:
        return float(self.centreline.s[-1])


def _profile(points: list[ProfilePoint], s: np.ndarray) -> np.ndarray:
    """Smooth (C1, no overshoot) interpolation of control points; constant beyond the ends."""
    xs = np.array([p.s_m for p in points])
    vs = np.array([p.value for p in points])
    if len(xs) == 1:
        return np.full_like(s, vs[0])
    return PchipInterpolator(xs, vs)(np.clip(s, xs[0], xs[-1]))


def _cumulative(values: np.ndarray, step: float) -> np.ndarray:
    out = np.zeros_like(values)
    out[1:] = np.cumsum(0.5 * (values[1:] + values[:-1])) * step
    return out


def build_centreline(road: RoadSpec) -> Centreline:
    s = np.arange(0.0, road.length_m + CENTRELINE_STEP_M / 2, CENTRELINE_STEP_M)
    heading = np.radians(road.heading_deg) + _cumulative(_profile(road.curvature, s), CENTRELINE_STEP_M)
    xy = np.stack([_cumulative(np.cos(heading), CENTRELINE_STEP_M),
                   _cumulative(np.sin(heading), CENTRELINE_STEP_M)], axis=1)
    grade = _profile(road.grade, s)
    tangent = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    return Centreline(s=s, xy=xy, heading=heading, z=_cumulative(grade, CENTRELINE_STEP_M), grade=grade,
                      tangent=tangent)


def build_cross_section(road: RoadSpec) -> CrossSection:
    """Crown falling at `crossfall` to the gutters, curb faces, sidewalks falling to the road, verges."""
    t = np.arange(-HALF_WIDTH_M, HALF_WIDTH_M + CROSS_STEP_M / 2, CROSS_STEP_M)
    a = np.abs(t)
    w = road.road_half_width_m
    gutter = -road.crossfall * w
    curb_top = w + CURB_FACE_M
    sidewalk_end = curb_top + 0.2 + road.sidewalk_width_m
    h = np.where(a <= w, -road.crossfall * a, 0.0)
    face = (a > w) & (a <= curb_top)
    h = np.where(face, gutter + road.curb_height_m * (a - w) / CURB_FACE_M, h)
    top = gutter + road.curb_height_m
    walk = (a > curb_top) & (a <= sidewalk_end)
    h = np.where(walk, top + SIDEWALK_FALL * (a - curb_top), h)
    h = np.where(a > sidewalk_end, top + SIDEWALK_FALL * (sidewalk_end - curb_top)
                 + VERGE_RISE * (a - sidewalk_end), h)
    slope = np.gradient(h, CROSS_STEP_M)
    return CrossSection(t0=float(t[0]), height=h.astype(np.float32), slope=slope.astype(np.float32))


def _project(cl: Centreline, points: np.ndarray) -> np.ndarray:
    """Arc length of the centre-line point nearest to each ENU point: the nearest of samples every
    10 m by brute force, then Newton steps along the tangent."""
    coarse = slice(None, None, 40)
    cx, cy, cs = cl.xy[coarse, 0].astype(np.float32), cl.xy[coarse, 1].astype(np.float32), cl.s[coarse]
    s = np.empty(len(points))
    for a in range(0, len(points), 100_000):
        p = points[a:a + 100_000].astype(np.float32)
        d2 = np.square(p[:, :1] - cx[None]) + np.square(p[:, 1:] - cy[None])
        s[a:a + 100_000] = cs[np.argmin(d2, axis=1)]
    for _ in range(6):
        x, y, tx, ty = _centreline_at(cl, s)
        s += (points[:, 0] - x) * tx + (points[:, 1] - y) * ty
    return s


def _centreline_at(cl: Centreline, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x, y and the unit tangent at arc lengths s (float64), extended straight beyond the ends."""
    s = np.asarray(s, np.float64)
    u = np.clip(s * (1 / CENTRELINE_STEP_M), 0, len(cl.s) - 1.000001)
    i = u.astype(np.int64)
    f = u - i
    g = 1 - f
    tx = cl.tangent[i, 0] * g + cl.tangent[i + 1, 0] * f
    ty = cl.tangent[i, 1] * g + cl.tangent[i + 1, 1] * f
    beyond = s - cl.s[i] - f * CENTRELINE_STEP_M
    x = cl.xy[i, 0] * g + cl.xy[i + 1, 0] * f + beyond * tx
    y = cl.xy[i, 1] * g + cl.xy[i + 1, 1] * f + beyond * ty
    return x, y, tx, ty


def _build_lookup(cl: Centreline) -> tuple[tuple[float, float], np.ndarray]:
    """(s, t) on a LOOKUP_RES_M ENU grid covering the corridor."""
    normal = np.stack([-cl.tangent[:, 1], cl.tangent[:, 0]], axis=1)
    reach = HALF_WIDTH_M + 2.0
    edges = np.concatenate([cl.xy + reach * normal, cl.xy - reach * normal])
    lo = np.floor(edges.min(axis=0)) - 2.0
    hi = np.ceil(edges.max(axis=0)) + 2.0
    cols, rows = (np.ceil((hi - lo) / LOOKUP_RES_M).astype(int) + 1).tolist()
    gx, gy = np.meshgrid(lo[0] + LOOKUP_RES_M * np.arange(cols), lo[1] + LOOKUP_RES_M * np.arange(rows))
    points = np.stack([gx.ravel(), gy.ravel()], axis=1)
    s = _project(cl, points)
    x, y, tx, ty = _centreline_at(cl, s)
    t = (ty * (x - points[:, 0]) - tx * (y - points[:, 1])) / np.hypot(tx, ty)
    st = np.stack([s, t], axis=1).astype(np.float32).reshape(rows, cols, 2)
    return (float(lo[0]), float(lo[1])), st


def _height_atlas(cl: Centreline, cross: CrossSection, atlas: RoadAtlas) -> np.ndarray:
    rows, cols = atlas.semantic.shape
    s = atlas.s0 + atlas.res * (np.arange(rows) + 0.5)
    t = atlas.t0 + atlas.res * (np.arange(cols) + 0.5)
    crown = np.interp(s, cl.s, cl.z).astype(np.float32)
    side = np.interp(t, cross.t0 + CROSS_STEP_M * np.arange(len(cross.height)), cross.height).astype(np.float32)
    return crown[:, None] + side[None, :]


def build_world(scenario: Scenario, seed: int | None = None) -> RoadWorld:
    """The whole road of a scenario, deterministic from the seed (the scenario's own by default)."""
    seed = scenario.seed if seed is None else seed
    cl = build_centreline(scenario.road)
    cross = build_cross_section(scenario.road)
    origin, st = _build_lookup(cl)
    atlas = paint_atlas(scenario.road, scenario.surface, float(cl.s[-1]), np.random.default_rng([seed, 1]))
    return RoadWorld(scenario, cl, cross, origin, st, atlas, _height_atlas(cl, cross, atlas))


# --- lookups (float32, through cv2.remap: bilinear weights in 1/32 steps of a cell) ---------------

def _remap(image: np.ndarray, u: np.ndarray, v: np.ndarray, interpolation: int,
           border: int = cv2.BORDER_REFLECT) -> np.ndarray:
    """cv2.remap for maps of any shape (OpenCV wants 2-D maps under 32767 on a side)."""
    shape = u.shape
    if u.ndim == 2 and max(shape) < 32767:
        return cv2.remap(image, u, v, interpolation, borderMode=border)
    n = u.size
    width = 4096
    rows = -(-n // width)
    pad = rows * width - n
    uu = np.pad(u.ravel(), (0, pad)).reshape(rows, width)
    vv = np.pad(v.ravel(), (0, pad)).reshape(rows, width)
    out = cv2.remap(image, uu, vv, interpolation, borderMode=border)
    return out.reshape(rows * width, *out.shape[2:])[:n].reshape(*shape, *out.shape[2:])


def road_coordinates(world: RoadWorld, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s, t) of ENU points (any shape, float32)."""
    u = (np.asarray(x, np.float32) - np.float32(world.lookup_origin[0])) * np.float32(1 / LOOKUP_RES_M)
    v = (np.asarray(y, np.float32) - np.float32(world.lookup_origin[1])) * np.float32(1 / LOOKUP_RES_M)
    st = _remap(world.lookup_st, u, v, cv2.INTER_LINEAR, cv2.BORDER_REPLICATE)  # beyond: the verge goes on
    return st[..., 0], st[..., 1]


def atlas_coordinates(world: RoadWorld, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Atlas pixel coordinates (column u, row v; texel centres at integers) of road coordinates.

    Beyond the atlas's sides the outermost verge carries on (the column is clamped)."""
    a = world.atlas
    u = (t - np.float32(a.t0 + a.res / 2)) * np.float32(1 / a.res)
    np.minimum(u, np.float32(a.semantic.shape[1] - 1), out=u)
    np.maximum(u, np.float32(0), out=u)
    v = (s - np.float32(a.s0 + a.res / 2)) * np.float32(1 / a.res)
    return u, v


def surface_uv(world: RoadWorld, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Atlas coordinates of ENU points."""
    return atlas_coordinates(world, *road_coordinates(world, x, y))


def height_uv(world: RoadWorld, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return _remap(world.height, u, v, cv2.INTER_LINEAR)


def albedo_uv(world: RoadWorld, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Linear RGB albedo * 255 (uint8, (..., 3)) of the painted surface."""
    return _remap(world.atlas.albedo, u, v, cv2.INTER_LINEAR)


def semantic_uv(world: RoadWorld, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Semantic class (uint8) of the surface."""
    return _remap(world.atlas.semantic, u, v, cv2.INTER_NEAREST)


def surface_height(world: RoadWorld, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Surface height at ENU (x, y), float32."""
    return height_uv(world, *surface_uv(world, x, y))


def centreline_frame(world: RoadWorld, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x, y and unit tangent (tx, ty) of the centre line at arc lengths s (float64)."""
    return _centreline_at(world.centreline, s)


def road_point(world: RoadWorld, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """ENU (x, y) of road coordinates (s, t), float64 (..., 2)."""
    x, y, tx, ty = _centreline_at(world.centreline, s)
    t = np.asarray(t, np.float64)
    return np.stack([x - ty * t, y + tx * t], axis=-1)


def height_st(world: RoadWorld, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Surface height at road coordinates, from the profiles directly (float64)."""
    cl, cross = world.centreline, world.cross
    tt = cross.t0 + CROSS_STEP_M * np.arange(len(cross.height))
    return np.interp(s, cl.s, cl.z) + np.interp(t, tt, cross.height.astype(np.float64))


# --- ground truth -------------------------------------------------------------------------------

@dataclass
class GroundTruthGrids:
    """ENU rasters: cell (row i, column j) covers x in origin_x + [j, j+1) * res, y in origin_y + [i, i+1) * res.

    Outside the corridor (|t| > GT_HALF_WIDTH_M or off the road's ends) elevation is NaN, semantic is
    NO_CLASS and albedo 0."""

    origin_xy: tuple[float, float]
    resolution: float
    elevation: np.ndarray  # (rows, cols) float32, ENU up (m)
    semantic: np.ndarray  # (rows, cols) uint8, SemanticClass ids
    albedo: np.ndarray  # (rows, cols, 3) uint8, linear RGB reflectance * 255


def ground_truth_grids(world: RoadWorld, s_range: tuple[float, float] | None = None,
                       res: float = GT_RES_M, half_width: float = GT_HALF_WIDTH_M) -> GroundTruthGrids:
    """Elevation, semantic class and albedo sampled at cell centres over the corridor |t| <= half_width."""
    cl = world.centreline
    s_lo, s_hi = s_range if s_range is not None else (0.0, float(cl.s[-1]))
    keep = (cl.s >= s_lo) & (cl.s <= s_hi)
    normal = np.stack([-np.sin(cl.heading[keep]), np.cos(cl.heading[keep])], axis=1)
    edges = np.concatenate([cl.xy[keep] + half_width * normal, cl.xy[keep] - half_width * normal])
    lo = np.floor(edges.min(axis=0) / res) * res
    hi = np.ceil(edges.max(axis=0) / res) * res
    cols, rows = np.rint((hi - lo) / res).astype(int).tolist()
    elevation = np.full((rows, cols), np.nan, np.float32)
    semantic = np.full((rows, cols), NO_CLASS, np.uint8)
    albedo = np.zeros((rows, cols, 3), np.uint8)
    xs = (lo[0] + res * (np.arange(cols) + 0.5)).astype(np.float32)
    block = max(1, 1_000_000 // cols)
    for r0 in range(0, rows, block):
        ys = (lo[1] + res * (np.arange(r0, min(rows, r0 + block)) + 0.5)).astype(np.float32)
        gx, gy = np.meshgrid(xs, ys)
        s, t = road_coordinates(world, gx, gy)
        inside = (np.abs(t) <= half_width) & (s >= s_lo) & (s <= s_hi)
        u, v = atlas_coordinates(world, s, t)
        rows_here = slice(r0, r0 + len(ys))
        elevation[rows_here] = np.where(inside, height_uv(world, u, v), np.nan)
        semantic[rows_here] = np.where(inside, semantic_uv(world, u, v), NO_CLASS)
        albedo[rows_here] = albedo_uv(world, u, v) * inside[..., None]
    return GroundTruthGrids((float(lo[0]), float(lo[1])), res, elevation, semantic, albedo)


def is_road_surface(classes: np.ndarray) -> np.ndarray:
    """Mask of the road-surface classes (road, lane marking, curb, manhole)."""
    return np.isin(classes, (SemanticClass.ROAD, SemanticClass.LANE_MARKING, SemanticClass.CURB,
                             SemanticClass.MANHOLE))
