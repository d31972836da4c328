"""One simulated drive's world state: the road, the ego car's motion, the other cars and the light, built
deterministically from a scenario, the car's config, a duration and a seed."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from daemon.spine.config import CarConfig
from sim.world.ego_trajectory import EgoTrajectory, drive_trajectory
from sim.world.road_world import CROSS_STEP_M, RoadWorld, build_world
from sim.world.scenarios import Scenario, with_camera_response
from sim.world.traffic import Traffic, place_traffic
from sim.world.tree_shadows import tree_shadow

HEADLIGHT_POSITION = np.array([3.7, 0.0, 0.2])  # vehicle frame (reference point at the rear axle)
HEADLIGHT_DIP_DEG = 1.5


@dataclass
class Scene:
    scenario: Scenario
    config: CarConfig  # with the scenario's camera responses
    seconds: float
    seed: int
    world: RoadWorld
    ego: EgoTrajectory
    traffic: Traffic
    sun_direction: np.ndarray  # (3,) unit vector towards the sun, ENU
    lit_atlas: np.ndarray | None  # (rows, cols, 3) uint8: albedo * daylight on each texel (day only)


def sun_direction(scenario: Scenario) -> np.ndarray:
    el, az = np.radians(scenario.lighting.sun_elevation_deg), np.radians(scenario.lighting.sun_azimuth_deg)
    return np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])  # azimuth from north


def _daylight_atlas(world: RoadWorld, sun: np.ndarray, shadow: np.ndarray | None = None) -> np.ndarray:
    """Albedo times (ambient + sun * cos incidence * (1 - shadow)), the surface normal from grade, crossfall
    and curbs; `shadow` is the fraction of direct sunlight each texel loses (sim/world/tree_shadows.py)."""
    light = world.scenario.lighting
    atlas = world.atlas
    rows, cols = atlas.semantic.shape
    s = atlas.s0 + atlas.res * (np.arange(rows) + 0.5)
    t = atlas.t0 + atlas.res * (np.arange(cols) + 0.5)
    cl = world.centreline
    tx = np.interp(s, cl.s, cl.tangent[:, 0])
    ty = np.interp(s, cl.s, cl.tangent[:, 1])
    grade = np.interp(s, cl.s, cl.grade)
    cross = world.cross
    slope = np.interp(t, cross.t0 + CROSS_STEP_M * np.arange(len(cross.slope)), cross.slope)
    # normal ~ up - grade * tangent - slope * left normal; shade = ambient + sun * max(0, n . sun)
    l_t = (sun[0] * tx + sun[1] * ty).astype(np.float32)  # sun along the tangent, per row
    l_n = (-sun[0] * ty + sun[1] * tx).astype(np.float32)  # along the left normal
    slope32 = slope.astype(np.float32)[None, :]
    dot = np.float32(sun[2]) - (grade.astype(np.float32) * l_t)[:, None] - l_n[:, None] * slope32
    norm = 1.0 / np.sqrt(np.float32(1.0) + (grade.astype(np.float32) ** 2)[:, None] + slope32 ** 2)
    np.multiply(dot, norm, out=dot)
    np.maximum(dot, 0, out=dot)
    if shadow is not None:
        np.multiply(dot, np.float32(1) - shadow, out=dot)
    shade = cv2.convertScaleAbs(dot, alpha=128.0 * light.sun, beta=128.0 * light.ambient)  # 128 = 1.0
    return cv2.multiply(atlas.albedo, cv2.merge([shade, shade, shade]), scale=1.0 / 128)


def build_scene(scenario: Scenario, config: CarConfig, seconds: float, seed: int | None = None,
                world_seed: int | None = None) -> Scene:
    """`seed` draws the drive (ego, traffic, noise); `world_seed` the road and its trees (default: `seed`)."""
    seed = scenario.seed if seed is None else seed
    world_seed = seed if world_seed is None else world_seed
    config = with_camera_response(config, scenario)
    world = build_world(scenario, world_seed)
    ego = drive_trajectory(world, config.vehicle, seconds, np.random.default_rng([seed, 2]))
    traffic = place_traffic(world, ego, seconds, np.random.default_rng([seed, 3]))
    sun = sun_direction(scenario)
    lit = None
    if scenario.lighting.mode == "day":
        lit = _daylight_atlas(world, sun, tree_shadow(world, sun, np.random.default_rng([world_seed, 11])))
    return Scene(scenario, config, seconds, seed, world, ego, traffic, sun, lit)
