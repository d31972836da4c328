"""Ray casting onto the road's height field: a coarse march that brackets the first crossing of each ray,
and a secant refinement from a good first guess (both vectorised over many rays)."""

from __future__ import annotations

import numpy as np

from sim.world.road_world import RoadWorld, height_uv, surface_uv

MAX_RANGE_M = 300.0
MARCH_STEPS = 56
HIT_TOLERANCE_M = 0.03
STEP_TOLERANCE_M = 0.25  # a ray that ends this close to the surface hit a step (a curb face)


def _gap(world: RoadWorld, origin: np.ndarray, directions: np.ndarray, t: np.ndarray):
    """Height of the ray point above the surface at distance t, and the point's atlas coordinates."""
    x = t * directions[..., 0]
    x += origin[..., 0]
    y = t * directions[..., 1]
    y += origin[..., 1]
    z = t * directions[..., 2]
    z += origin[..., 2]
    u, v = surface_uv(world, x, y)
    return z - height_uv(world, u, v), u, v


def march(world: RoadWorld, origin: np.ndarray, directions: np.ndarray, t_max: float = MAX_RANGE_M) -> np.ndarray:
    """Distance to the first surface crossing of each ray (N,), inf where none within t_max.

    origin (3,) or (N, 3); directions (N, 3) unit vectors, float32."""
    origin = np.asarray(origin, np.float32)
    steps = np.geomspace(0.3, t_max, MARCH_STEPS).astype(np.float32)[:, None]  # (K, 1)
    gap, _, _ = _gap(world, origin[None] if origin.ndim == 2 else origin, directions[None], steps)
    below = gap < 0
    first = np.argmax(below, axis=0)
    hit = below[first, np.arange(directions.shape[0])] & (first > 0)
    k = np.maximum(first, 1)
    cols = np.arange(directions.shape[0])
    lo, hi = steps[k - 1, 0], steps[k, 0]
    f_lo, f_hi = gap[k - 1, cols], gap[k, cols]
    for _ in range(4):  # false position inside the bracket
        t_mid = lo + (hi - lo) * np.clip(f_lo / np.where(f_lo - f_hi == 0, 1, f_lo - f_hi), 0.02, 0.98)
        f_mid, _, _ = _gap(world, origin, directions, t_mid)
        above = f_mid > 0
        lo, f_lo = np.where(above, t_mid, lo), np.where(above, f_mid, f_lo)
        hi, f_hi = np.where(above, hi, t_mid), np.where(above, f_hi, f_mid)
    t = lo + (hi - lo) * np.clip(f_lo / np.where(f_lo - f_hi == 0, 1, f_lo - f_hi), 0, 1)
    return np.where(hit, t, np.inf).astype(np.float32)


def refine(world: RoadWorld, origin: np.ndarray, directions: np.ndarray, t0: np.ndarray, iterations: int = 2,
           t_max: float = MAX_RANGE_M) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Secant steps from first guesses t0 (finite) to the surface crossing.

    Returns (t, u, v, hit): distance, atlas coordinates of the point and whether it lies on the surface
    inside t_max (within HIT_TOLERANCE_M where the surface is smooth, STEP_TOLERANCE_M at a step)."""
    origin = np.asarray(origin, np.float32)
    t_a = np.clip(t0, 0.1, t_max).astype(np.float32)
    f_a, u, v = _gap(world, origin, directions, t_a)
    t_b = t_a * np.float32(1.01) + np.float32(0.01)
    f_b, u, v = _gap(world, origin, directions, t_b)
    for _ in range(iterations):
        denom = f_b - f_a
        safe = np.abs(denom) > 1e-7
        step = np.where(safe, f_b * (t_b - t_a) / np.where(safe, denom, 1), 0)
        t_new = np.clip(t_b - step, 0.1, 1.5 * t_max).astype(np.float32)
        t_a, f_a = t_b, f_b
        t_b = t_new
        f_b, u, v = _gap(world, origin, directions, t_b)
    hit = (np.abs(f_b) < STEP_TOLERANCE_M) & (t_b < t_max)
    return t_b, u, v, hit
