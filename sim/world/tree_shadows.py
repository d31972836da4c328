"""Shadows of roadside trees on the painted surface: trees beyond the sidewalks (their trunks and crowns are
not drawn, only where they keep the sun off), as the fraction of direct sunlight each atlas texel loses."""

from __future__ import annotations

import cv2
import numpy as np

from sim.world.road_atlas import ATLAS_RES_M, CURB_WIDTH_M, DRAW_SHIFT, HALF_WIDTH_M
from sim.world.road_world import RoadWorld

MIN_SUN_ELEVATION_DEG = 5.0  # a lower sun casts shadows too long to draw: none are
TRUNK_RADIUS_M = 0.15
PENUMBRA_M = 0.05  # the sun's disc blurs a shadow's edge by ~1 cm per metre from the crown; ~5 cm here


def _px(s: float, t: float) -> tuple[int, int]:
    """Atlas pixel (column, row) of road coordinates, in cv2's fixed point."""
    return (int(round((t + HALF_WIDTH_M) / ATLAS_RES_M * (1 << DRAW_SHIFT))),
            int(round(s / ATLAS_RES_M * (1 << DRAW_SHIFT))))


def tree_shadow(world: RoadWorld, sun: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
    """(atlas rows, cols) float32 in [0, 1]: how much of the direct sunlight each texel loses (None: no trees,
    or the sun too low). Trees stand in rows on both sides, `lighting.trees_per_100m` per side, a crown of
    `tree_crown_radius_m` at `tree_height_m`, each with its own size, spacing and leaf density."""
    light, road = world.scenario.lighting, world.scenario.road
    elevation = np.arcsin(np.clip(sun[2], -1, 1))
    if light.trees_per_100m <= 0 or np.degrees(elevation) < MIN_SUN_ELEVATION_DEG:
        return None
    rows, cols = world.atlas.semantic.shape
    canvas = np.zeros((rows, cols), np.uint8)
    length = world.length_m
    cl = world.centreline
    away = -np.asarray(sun[:2], np.float64) / max(np.hypot(sun[0], sun[1]), 1e-9)  # shadows point away from the sun
    spacing = 100.0 / light.trees_per_100m
    trunk_t = road.road_half_width_m + CURB_WIDTH_M + road.sidewalk_width_m + light.tree_setback_m
    for side in (-1.0, 1.0):
        s = rng.uniform(0, spacing)
        while s < length:
            height = light.tree_height_m * rng.uniform(0.75, 1.25)
            radius = light.tree_crown_radius_m * rng.uniform(0.7, 1.3)
            density = rng.uniform(0.65, 0.95)  # light through the leaves
            t = side * (trunk_t + rng.uniform(0, 0.5))
            tx, ty = np.interp(s, cl.s, cl.tangent[:, 0]), np.interp(s, cl.s, cl.tangent[:, 1])
            ds, dt = away[0] * tx + away[1] * ty, -away[0] * ty + away[1] * tx  # in road coordinates
            reach = height / np.tan(elevation)
            centre = _px(s + ds * reach, t + dt * reach)
            axes = (int(radius / np.sin(elevation) / ATLAS_RES_M * (1 << DRAW_SHIFT)),
                    int(radius / ATLAS_RES_M * (1 << DRAW_SHIFT)))
            angle = float(np.degrees(np.arctan2(ds, dt)))  # the major axis along the shadow (x: columns, y: rows)
            value = int(255 * density)
            cv2.ellipse(canvas, centre, axes, angle, 0, 360, value, -1, cv2.LINE_AA, DRAW_SHIFT)
            trunk_end = _px(s + ds * (reach - radius), t + dt * (reach - radius))
            width = max(1, int(round(2 * TRUNK_RADIUS_M / ATLAS_RES_M)))
            cv2.line(canvas, _px(s, t), trunk_end, 255, width, cv2.LINE_AA, DRAW_SHIFT)
            s += spacing * rng.uniform(0.8, 1.2)
    blurred = cv2.GaussianBlur(canvas, (0, 0), PENUMBRA_M / ATLAS_RES_M)
    return blurred.astype(np.float32) * np.float32(1 / 255)
