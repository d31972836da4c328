"""The painted road surface in road coordinates (s along the centre line, t to its left): albedo and
semantic class at ATLAS_RES_M, drawn procedurally: textured asphalt with patches, cracks and stains,
solid and dashed lane markings (faded or partly worn away), painted arrows, manholes, curbs (plain or in
alternating painted blocks), paved sidewalks and grass verges, in the materials of the scenario's surface."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from daemon.spine.semantic_classes import SemanticClass
from sim.world.scenarios import RoadSpec, SurfaceSpec

ATLAS_RES_M = 0.025
HALF_WIDTH_M = 20.0
CURB_WIDTH_M = 0.2  # curb stone: face plus top, class CURB
MANHOLE_RADIUS_M = 0.32
PAVER_M = 0.3
DRAW_SHIFT = 4  # cv2 sub-pixel drawing bits

# Materials (indices into the palette of a scenario's surface, sim/world/scenarios.py SurfaceSpec).
ASPHALT, PATCH_DARK, PATCH_LIGHT, MARKING, CURB, SIDEWALK, VERGE, MANHOLE, CURB_STRIPE = range(9)
TEXTURE_STRENGTH = np.array([0.16, 0.12, 0.14, 0.10, 0.10, 0.12, 0.35, 0.10], np.float32)  # asphalt, curb: surface's


def palette(surface: SurfaceSpec) -> np.ndarray:
    """(9, 3) float32 linear RGB albedo of each material; the paint faded towards the asphalt by its contrast."""
    paint = surface.paint_rgb
    if surface.paint_contrast != 1.0:
        paint = tuple(a + surface.paint_contrast * (p - a) for a, p in zip(surface.asphalt_rgb, paint, strict=True))
    stripe = surface.curb_stripe_rgb if surface.curb_stripe_rgb is not None else surface.curb_rgb
    return np.array([surface.asphalt_rgb, surface.patch_dark_rgb, surface.patch_light_rgb, paint, surface.curb_rgb,
                     surface.sidewalk_rgb, surface.verge_rgb, surface.manhole_rgb, stripe], np.float32)


def texture_strength(surface: SurfaceSpec) -> np.ndarray:
    """(9,) float32 relative albedo variation of each material."""
    strength = np.append(TEXTURE_STRENGTH, np.float32(surface.curb_texture))
    strength[ASPHALT] = surface.asphalt_texture
    strength[CURB] = surface.curb_texture
    return strength


@dataclass
class RoadAtlas:
    """Texel (row i, column j) covers s in s0 + [i, i+1) * res and t in t0 + [j, j+1) * res."""

    s0: float
    t0: float
    res: float
    albedo: np.ndarray  # (rows, cols, 3) uint8, linear RGB * 255
    semantic: np.ndarray  # (rows, cols) uint8


def _col(t: float) -> float:
    return (t + HALF_WIDTH_M) / ATLAS_RES_M


def _row(s: float) -> float:
    return s / ATLAS_RES_M


def _poly(points_st: np.ndarray) -> np.ndarray:
    """(s, t) polygon -> cv2 fixed-point (x = column, y = row) polygon."""
    xy = np.stack([(points_st[:, 1] + HALF_WIDTH_M) / ATLAS_RES_M, points_st[:, 0] / ATLAS_RES_M], axis=1)
    return np.rint(xy * (1 << DRAW_SHIFT)).astype(np.int32)


def _fill(canvas: np.ndarray, points_st: np.ndarray, value: int) -> None:
    cv2.fillPoly(canvas, [_poly(points_st)], int(value), lineType=cv2.LINE_8, shift=DRAW_SHIFT)


def _rect(s0: float, s1: float, t0: float, t1: float) -> np.ndarray:
    return np.array([[s0, t0], [s0, t1], [s1, t1], [s1, t0]])


def lane_boundaries(road: RoadSpec) -> np.ndarray:
    """t of each lane boundary, right edge (lane 0's right side) first."""
    w = road.lanes * road.lane_width_m
    return -w / 2 + road.lane_width_m * np.arange(road.lanes + 1)


def lane_centre(road: RoadSpec, lane: int) -> float:
    return float(lane_boundaries(road)[lane] + road.lane_width_m / 2)


def lane_forward(road: RoadSpec, lane: int) -> bool:
    """Right-hand traffic: the right half of the lanes runs towards +s."""
    return lane < (road.lanes + 1) // 2


def _paint_markings(road: RoadSpec, length: float, material: np.ndarray, classes: np.ndarray,
                    rng: np.random.Generator) -> None:
    half = road.marking_width_m / 2
    bounds = lane_boundaries(road)
    centre = road.lanes // 2 if road.lanes % 2 == 0 else -1
    period = road.dash_length_m + road.dash_gap_m
    for k, t in enumerate(bounds):
        solid = k in (0, road.lanes) or (k == centre and road.lanes >= 4)
        if solid:
            pieces = [(0.0, length)]
        else:
            phase = rng.uniform(0, period)
            starts = np.arange(phase - period, length, period)
            pieces = [(a, a + road.dash_length_m) for a in starts]
        for a, b in pieces:
            quad = _rect(a, b, t - half, t + half)
            _fill(material, quad, MARKING)
            _fill(classes, quad, SemanticClass.LANE_MARKING)
    for lane in range(road.lanes):
        forward = lane_forward(road, lane)
        tc = lane_centre(road, lane)
        for s in np.arange(road.arrow_spacing_m / 2 + rng.uniform(0, 10), length - 10, road.arrow_spacing_m):
            d = 1.0 if forward else -1.0
            shaft = np.array([[s - 2.0 * d, tc - 0.08], [s + 0.6 * d, tc - 0.08],
                              [s + 0.6 * d, tc + 0.08], [s - 2.0 * d, tc + 0.08]])
            head = np.array([[s + 0.6 * d, tc - 0.35], [s + 2.0 * d, tc], [s + 0.6 * d, tc + 0.35]])
            for poly in (shaft, head):
                _fill(material, poly, MARKING)
                _fill(classes, poly, SemanticClass.LANE_MARKING)


def _paint_manholes(road: RoadSpec, length: float, material: np.ndarray, classes: np.ndarray,
                    shade: np.ndarray, rng: np.random.Generator) -> None:
    r_px = MANHOLE_RADIUS_M / ATLAS_RES_M
    for s in np.arange(rng.uniform(5, road.manhole_spacing_m), length - 5, road.manhole_spacing_m):
        s = s + rng.uniform(-3, 3)
        lane = int(rng.integers(road.lanes))
        t = lane_centre(road, lane) + rng.uniform(-0.9, 0.9)
        centre = (int(round(_col(t) * 16)), int(round(_row(s) * 16)))
        cv2.circle(material, centre, int(r_px * 16), MANHOLE, -1, cv2.LINE_8, DRAW_SHIFT)
        cv2.circle(classes, centre, int(r_px * 16), int(SemanticClass.MANHOLE), -1, cv2.LINE_8, DRAW_SHIFT)
        cv2.circle(shade, centre, int((r_px - 1) * 16), 1.5, 2, cv2.LINE_AA, DRAW_SHIFT)
        for ring in (0.45, 0.7):
            cv2.circle(shade, centre, int(r_px * ring * 16), 0.55, 2, cv2.LINE_AA, DRAW_SHIFT)
        for angle in np.arange(0, np.pi, np.pi / 4):
            dx, dy = np.cos(angle) * r_px * 0.7, np.sin(angle) * r_px * 0.7
            p0 = (int((centre[0] / 16 - dx) * 16), int((centre[1] / 16 - dy) * 16))
            p1 = (int((centre[0] / 16 + dx) * 16), int((centre[1] / 16 + dy) * 16))
            cv2.line(shade, p0, p1, 0.65, 1, cv2.LINE_AA, DRAW_SHIFT)


def _paint_wear(road: RoadSpec, length: float, material: np.ndarray, shade: np.ndarray,
                rng: np.random.Generator) -> None:
    """Patches (as material), cracks and stains (as shade) on the carriageway."""
    w = road.road_half_width_m
    per_100 = length / 100.0
    for _ in range(rng.poisson(road.patches_per_100m * per_100)):
        s, t = rng.uniform(0, length), rng.uniform(-w + 1, w - 1)
        ls, lt = rng.uniform(1.0, 5.0), rng.uniform(0.8, 3.0)
        a = rng.normal(0, 0.15)
        corners = np.array([[-ls, -lt], [-ls, lt], [ls, lt], [ls, -lt]]) / 2
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        _fill(material, corners @ rot.T + [s, t], PATCH_DARK if rng.random() < 0.6 else PATCH_LIGHT)
    for _ in range(rng.poisson(road.cracks_per_100m * per_100)):
        n = int(rng.integers(8, 40))
        heading = rng.uniform(0, 2 * np.pi) if rng.random() < 0.6 else rng.choice([0.0, np.pi])
        steps = np.cumsum(rng.normal(0, 0.5, n)) + heading
        ds = rng.uniform(0.05, 0.15)
        pts = np.cumsum(np.stack([np.cos(steps), np.sin(steps)], axis=1) * ds, axis=0)
        pts += [rng.uniform(0, length), rng.uniform(-w, w)]
        cv2.polylines(shade, [_poly(pts)], False, float(rng.uniform(0.35, 0.6)), 1, cv2.LINE_AA, DRAW_SHIFT)
    for _ in range(rng.poisson(road.stains_per_100m * per_100)):
        s, t = rng.uniform(0, length), rng.uniform(-w, w)
        axes = (int(rng.uniform(0.3, 1.2) / ATLAS_RES_M * 16), int(rng.uniform(0.2, 0.7) / ATLAS_RES_M * 16))
        cv2.ellipse(shade, (int(_col(t) * 16), int(_row(s) * 16)), axes, float(rng.uniform(0, 180)), 0, 360,
                    float(rng.uniform(0.6, 0.8)), -1, cv2.LINE_AA, DRAW_SHIFT)


def _wear_paint(surface: SurfaceSpec, material: np.ndarray, classes: np.ndarray, rng: np.random.Generator) -> None:
    """Wear `paint_missing` of the painted area away in fragments about `paint_wear_m` across: asphalt and
    road there (a worn-off marking is no marking, in the truth as in the images)."""
    painted = material == MARKING
    if surface.paint_missing <= 0 or not painted.any():
        return
    cols = np.flatnonzero(painted.any(axis=0))  # only the columns markings cross
    lo, hi = int(cols[0]), int(cols[-1]) + 1
    noise = _noise(rng, (material.shape[0], hi - lo), max(1, round(surface.paint_wear_m / ATLAS_RES_M)))
    band = painted[:, lo:hi]
    gone = band & (noise < np.quantile(noise[band], surface.paint_missing))
    material[:, lo:hi][gone] = ASPHALT
    classes[:, lo:hi][gone] = SemanticClass.ROAD


def _noise(rng: np.random.Generator, shape: tuple[int, int], scale_texels: int) -> np.ndarray:
    """Smooth unit-variance noise with features of about scale_texels."""
    small = rng.standard_normal((shape[0] // scale_texels + 2, shape[1] // scale_texels + 2), dtype=np.float32)
    big = cv2.resize(small, ((shape[1] // scale_texels + 2) * scale_texels,
                             (shape[0] // scale_texels + 2) * scale_texels), interpolation=cv2.INTER_CUBIC)
    return big[: shape[0], : shape[1]]


def paint_atlas(road: RoadSpec, surface: SurfaceSpec, length: float, rng: np.random.Generator) -> RoadAtlas:
    rows = int(np.ceil(length / ATLAS_RES_M)) + 1
    cols = int(round(2 * HALF_WIDTH_M / ATLAS_RES_M))
    t = -HALF_WIDTH_M + ATLAS_RES_M * (np.arange(cols) + 0.5)
    a = np.abs(t)
    w = road.road_half_width_m
    walk_end = w + CURB_WIDTH_M + road.sidewalk_width_m
    band_material = np.select([a <= w, a <= w + CURB_WIDTH_M, a <= walk_end],
                              [ASPHALT, CURB, SIDEWALK], VERGE).astype(np.uint8)
    band_class = np.select([a <= w - 0.03, a <= w + CURB_WIDTH_M],
                           [SemanticClass.ROAD, SemanticClass.CURB], SemanticClass.BACKGROUND).astype(np.uint8)
    material = np.ascontiguousarray(np.broadcast_to(band_material, (rows, cols)))
    classes = np.ascontiguousarray(np.broadcast_to(band_class, (rows, cols)))
    shade = np.ones((rows, cols), np.float32)

    _paint_wear(road, length, material, shade, rng)
    _paint_markings(road, length, material, classes, rng)
    _paint_manholes(road, length, material, classes, shade, rng)
    _wear_paint(surface, material, classes, rng)
    if surface.curb_stripe_rgb is not None:
        curb_cols = band_material == CURB
        stripe_rows = (ATLAS_RES_M * (np.arange(rows) + 0.5) // surface.curb_stripe_m) % 2 == 1
        material[np.ix_(stripe_rows, curb_cols)] = CURB_STRIPE

    # Paving-stone joints on the sidewalks.
    walk_cols = (a > w + CURB_WIDTH_M) & (a <= walk_end)
    s_rows = ATLAS_RES_M * (np.arange(rows) + 0.5)
    joint_rows = (s_rows % PAVER_M) < ATLAS_RES_M
    joint_cols = walk_cols & (((a - w - CURB_WIDTH_M) % PAVER_M) < ATLAS_RES_M)
    shade[np.ix_(joint_rows, walk_cols)] *= 0.7
    shade[:, joint_cols] *= 0.7

    texture = rng.random((rows, cols), dtype=np.float32)
    texture -= 0.5
    texture *= 2.0
    texture += _noise(rng, (rows, cols), max(1, round(surface.texture_fine_m / ATLAS_RES_M))) * 0.6
    texture += _noise(rng, (rows, cols), max(1, round(surface.texture_coarse_m / ATLAS_RES_M))) * 0.5
    texture *= texture_strength(surface)[material]
    texture += 1.0
    texture *= shade
    albedo = np.empty((rows, cols, 3), np.uint8)
    colours = palette(surface)
    for c in range(3):
        channel = colours[:, c][material]
        channel *= texture
        albedo[..., c] = cv2.convertScaleAbs(channel, alpha=255.0, beta=0.5)
    return RoadAtlas(s0=0.0, t0=-HALF_WIDTH_M, res=ATLAS_RES_M, albedo=albedo, semantic=classes)
