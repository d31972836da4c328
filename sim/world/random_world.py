"""Random worlds (`roadlog simulate --scenario random --seed N`): a whole scenario drawn from a seed, every
parameter within the realistic range RANGES states for it: the road's lanes, markings, dash pattern, paint
wear, kerbs, grades and crossfall, the asphalt and the other materials, sun, tree shadows and exposure, each
camera's response, traffic and parked cars. The same seed draws the same world."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sim.world.scenarios import Scenario, load_scenario

RANDOM = "random"  # the scenario name that draws a world
ROAD_LENGTH_M = 500.0
DEFAULT_SECONDS = 20.0

# Dash (length, gap) of lane lines as countries paint them.
DASH_PATTERNS_M = {
    "3/6 (Germany, in town)": (3.0, 6.0),
    "3/9": (3.0, 9.0),
    "3.05/9.15 (US, 10/30 ft)": (3.05, 9.15),
    "4.5/7.5": (4.5, 7.5),
    "6/12 (Germany, rural roads and motorways)": (6.0, 12.0),
}
# Kerbs: (colour, stripe colour or None, texture strength range) before a brightness of +-15 %.
KERBS = {
    "grey concrete": ((0.36, 0.35, 0.33), None, (0.06, 0.14)),
    "granite": ((0.25, 0.25, 0.26), None, (0.18, 0.30)),
    "red/white painted": ((0.66, 0.66, 0.63), (0.45, 0.06, 0.05), (0.04, 0.10)),
}
PAINTS = {"white": (0.70, 0.70, 0.66), "yellow": (0.68, 0.54, 0.12)}  # before a brightness of +-10 %
PAINT_WEIGHTS = (0.75, 0.25)
SIDEWALKS = {"red pavers": (0.30, 0.26, 0.24), "grey pavers": (0.30, 0.30, 0.29), "asphalt": (0.16, 0.16, 0.16)}
VERGES = {"grass": (0.09, 0.15, 0.05), "dry grass": (0.20, 0.18, 0.10)}

# The range every drawn value stays in: dotted path (`[]` for each list item, `*` for each camera) -> (lo, hi);
# for a colour, every channel's. Uniform draws take their bounds from here; a choice's range is its envelope.
RANGES: dict[str, tuple[float, float]] = {
    "origin.latitude_deg": (-55.0, 60.0),
    "origin.longitude_deg": (-180.0, 180.0),
    "origin.altitude_m": (0.0, 1500.0),
    "road.length_m": (ROAD_LENGTH_M, ROAD_LENGTH_M),
    "road.heading_deg": (-180.0, 180.0),
    "road.lanes": (2, 4),
    "road.lane_width_m": (2.75, 3.75),
    "road.crossfall": (0.01, 0.04),
    "road.curb_height_m": (0.08, 0.20),
    "road.gutter_m": (0.2, 0.6),
    "road.sidewalk_width_m": (1.5, 4.0),
    "road.marking_width_m": (0.10, 0.30),
    "road.dash_length_m": (3.0, 6.0),
    "road.dash_gap_m": (6.0, 12.0),
    "road.arrow_spacing_m": (30.0, 90.0),
    "road.manhole_spacing_m": (15.0, 50.0),
    "road.patches_per_100m": (0.0, 10.0),
    "road.cracks_per_100m": (0.0, 60.0),
    "road.stains_per_100m": (0.0, 15.0),
    "road.grade[].s_m": (0.0, ROAD_LENGTH_M),
    "road.grade[].value": (-0.08, 0.08),
    "grade_spacing_m": (30.0, 70.0),
    "road.curvature[].s_m": (0.0, ROAD_LENGTH_M),
    "road.curvature[].value": (-1 / 80, 1 / 80),  # radius >= 80 m
    "curvature_spacing_m": (40.0, 100.0),
    "surface.asphalt_grey": (0.06, 0.20),
    "surface.asphalt_rgb": (0.06 * 0.96, 0.20 * 1.06),  # grey with a tint of -4..+4 % red, -4..+6 % blue
    "surface.asphalt_texture": (0.08, 0.25),
    "surface.texture_fine_m": (0.2, 0.8),
    "surface.texture_coarse_m": (2.0, 8.0),
    "patch_dark_factor": (0.5, 0.75),
    "surface.patch_dark_rgb": (0.06 * 0.96 * 0.5, 0.20 * 1.06 * 0.75),
    "patch_light_factor": (1.2, 1.6),
    "surface.patch_light_rgb": (0.06 * 0.96 * 1.2, 0.20 * 1.06 * 1.6),
    "paint_brightness": (0.9, 1.1),
    "surface.paint_rgb": (0.12 * 0.9, 0.70 * 1.1),
    "surface.paint_contrast": (0.35, 1.0),
    "surface.paint_missing": (0.0, 0.35),
    "surface.paint_wear_m": (0.1, 0.6),
    "kerb_brightness": (0.85, 1.15),
    "surface.curb_rgb": (0.25 * 0.85, 0.66 * 1.15),
    "surface.curb_texture": (0.04, 0.30),
    "surface.curb_stripe_rgb": (0.05 * 0.85, 0.45 * 1.15),
    "surface.curb_stripe_m": (0.5, 1.0),
    "material_brightness": (0.85, 1.15),
    "surface.sidewalk_rgb": (0.16 * 0.85, 0.30 * 1.15),
    "verge_brightness": (0.7, 1.3),
    "surface.verge_rgb": (0.05 * 0.7, 0.20 * 1.3),
    "manhole_brightness": (0.8, 1.3),
    "surface.manhole_rgb": (0.09 * 0.8, 0.10 * 1.3),
    "lighting.ambient": (0.25, 0.6),
    "lighting.sun": (0.3, 1.0),
    "lighting.sun_elevation_deg": (15.0, 70.0),
    "lighting.sun_azimuth_deg": (0.0, 360.0),
    "lighting.exposure": (0.75, 1.3),
    "lighting.noise_scale": (0.7, 1.5),
    "lighting.fog_distance_m": (150.0, 600.0),
    "lighting.trees_per_100m": (0.0, 15.0),
    "lighting.tree_height_m": (5.0, 14.0),
    "lighting.tree_crown_radius_m": (1.5, 4.0),
    "lighting.tree_setback_m": (0.3, 3.0),
    "cameras.*.gain": (0.6, 1.4),
    "cameras.*.gamma": (0.85, 1.2),
    "cameras.*.white_balance": (0.85, 1.15),  # red and blue; green stays 1
    "cameras.*.saturation": (0.7, 1.3),
    "cameras.*.vignetting": (0.0, 0.35),
    "cameras.*.noise_sigma": (1.0, 3.0),
    "traffic.parked_cars_per_100m": (0.0, 12.0),
    "traffic.moving_cars": (0, 30),
    "traffic.lead_car_gap_m": (15.0, 40.0),
    "drive.speed_mps": (7.0, 13.0),
    "drive.speed_variation_mps": (0.0, 0.8),
    "drive.start_s_m": (20.0, 20.0),
    "drive.default_seconds": (DEFAULT_SECONDS, DEFAULT_SECONDS),
}
GRADE_STEP = 0.05  # the most the grade changes from one control point to the next (30-70 m on)
NONE_PROBABILITY = {"paint_missing": 0.3, "trees": 0.4, "lead_car": 0.6}  # worlds with fresh paint, no trees ...


class _Draw:
    """Uniform draws within RANGES, and choices, from one generator."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng([seed, 100])

    def u(self, key: str) -> float:
        return float(self.rng.uniform(*RANGES[key]))

    def chance(self, p: float) -> bool:
        return bool(self.rng.random() < p)

    def choice(self, table: dict, kinds: dict | None = None, what: str = "", weights: Sequence[float] | None = None):
        """A value of the table (with these probabilities, else all equally likely); its key goes into kinds[what]."""
        key = list(table)[int(self.rng.choice(len(table), p=weights))]
        if kinds is not None:
            kinds[what] = key
        return table[key]


def _profile(d: _Draw, name: str, spacing_key: str, step: float, zero_p: float) -> list[dict]:
    """Control points every `spacing_key` metres, each uniform over the range within `step` of the one before
    (so grades change over vertical curves a road would have), 0 with probability zero_p."""
    lo, hi = RANGES[f"road.{name}[].value"]
    points, s, value = [], 0.0, 0.0
    while s < ROAD_LENGTH_M:
        near = (max(lo, value - step), min(hi, value + step))
        value = 0.0 if d.chance(zero_p) else float(d.rng.uniform(*near))
        points.append({"s_m": round(s, 3), "value": value})
        s += d.u(spacing_key)
    return points


def _scaled(rgb: Sequence[float], factor: float) -> list[float]:
    return [min(1.0, c * factor) for c in rgb]


def _surface(d: _Draw, kinds: dict) -> dict:
    grey = d.u("surface.asphalt_grey")
    asphalt = [grey * (1 + d.rng.uniform(-0.04, 0.04)), grey, grey * (1 + d.rng.uniform(-0.04, 0.06))]
    kerb, stripe, texture = d.choice(KERBS, kinds, "kerb")
    kerb_brightness = d.u("kerb_brightness")
    return {
        "asphalt_rgb": asphalt,
        "asphalt_texture": d.u("surface.asphalt_texture"),
        "texture_fine_m": d.u("surface.texture_fine_m"),
        "texture_coarse_m": d.u("surface.texture_coarse_m"),
        "patch_dark_rgb": _scaled(asphalt, d.u("patch_dark_factor")),
        "patch_light_rgb": _scaled(asphalt, d.u("patch_light_factor")),
        "paint_rgb": _scaled(d.choice(PAINTS, kinds, "paint", PAINT_WEIGHTS), d.u("paint_brightness")),
        "paint_contrast": d.u("surface.paint_contrast"),
        "paint_missing": 0.0 if d.chance(NONE_PROBABILITY["paint_missing"]) else d.u("surface.paint_missing"),
        "paint_wear_m": d.u("surface.paint_wear_m"),
        "curb_rgb": _scaled(kerb, kerb_brightness),
        "curb_texture": float(d.rng.uniform(*texture)),
        "curb_stripe_rgb": None if stripe is None else _scaled(stripe, kerb_brightness),
        "curb_stripe_m": d.u("surface.curb_stripe_m"),
        "sidewalk_rgb": _scaled(d.choice(SIDEWALKS, kinds, "sidewalk"), d.u("material_brightness")),
        "verge_rgb": _scaled(d.choice(VERGES, kinds, "verge"), d.u("verge_brightness")),
        "manhole_rgb": _scaled((0.10, 0.095, 0.09), d.u("manhole_brightness")),
    }


def _lighting(d: _Draw) -> dict:
    most_trees = RANGES["lighting.trees_per_100m"][1]
    trees = 0.0 if d.chance(NONE_PROBABILITY["trees"]) else float(d.rng.uniform(2.0, most_trees))
    return {"mode": "day", **{k: d.u(f"lighting.{k}") for k in (
        "ambient", "sun", "sun_elevation_deg", "sun_azimuth_deg", "exposure", "noise_scale", "fog_distance_m")},
        "trees_per_100m": trees, "tree_height_m": d.u("lighting.tree_height_m"),
        "tree_crown_radius_m": d.u("lighting.tree_crown_radius_m"), "tree_setback_m": d.u("lighting.tree_setback_m")}


def _camera(d: _Draw) -> dict:
    lo, hi = RANGES["cameras.*.white_balance"]
    return {"gain": d.u("cameras.*.gain"), "gamma": d.u("cameras.*.gamma"),
            "white_balance": [float(d.rng.uniform(lo, hi)), 1.0, float(d.rng.uniform(lo, hi))],
            "saturation": d.u("cameras.*.saturation"), "vignetting": d.u("cameras.*.vignetting"),
            "noise_sigma": d.u("cameras.*.noise_sigma")}


def _lanes_and_traffic(d: _Draw) -> tuple[int, int, dict]:
    """Lane count, the ego lane and the traffic: parked cars only on an outer lane that is not the ego's."""
    lanes = int(d.rng.integers(2, 5))
    parking: list[int] = []
    if lanes == 4 and d.chance(0.6):
        parking = [0, 3]
    elif lanes == 3 and d.chance(0.5):
        parking = [0]
    forward = [k for k in range((lanes + 1) // 2) if k not in parking]
    ego = forward[int(d.rng.integers(len(forward)))]
    lo, hi = RANGES["traffic.moving_cars"]
    traffic = {"parking_lanes": parking,
               "parked_cars_per_100m": float(d.rng.uniform(2.0, RANGES["traffic.parked_cars_per_100m"][1]))
               if parking else 0.0,
               "moving_cars": int(d.rng.integers(lo, hi + 1)),
               "lead_car_gap_m": None if d.chance(NONE_PROBABILITY["lead_car"]) else d.u("traffic.lead_car_gap_m")}
    return lanes, ego, traffic


def draw_scenario(seed: int, camera_names: Sequence[str]) -> Scenario:
    """The random world of a seed, for a car with these cameras (each gets its own photometric response)."""
    d = _Draw(seed)
    kinds: dict[str, str] = {}
    lanes, ego, traffic = _lanes_and_traffic(d)
    dash, gap = d.choice(DASH_PATTERNS_M, kinds, "dashes")
    road = {"length_m": ROAD_LENGTH_M, "heading_deg": d.u("road.heading_deg"), "lanes": lanes,
            **{k: d.u(f"road.{k}") for k in ("lane_width_m", "crossfall", "curb_height_m", "gutter_m",
                                             "sidewalk_width_m", "marking_width_m", "arrow_spacing_m",
                                             "manhole_spacing_m", "patches_per_100m", "cracks_per_100m",
                                             "stains_per_100m")},
            "dash_length_m": dash, "dash_gap_m": gap,
            "grade": _profile(d, "grade", "grade_spacing_m", GRADE_STEP, 0.1),
            "curvature": _profile(d, "curvature", "curvature_spacing_m", 1 / 80, 0.4)}
    data = {
        "name": RANDOM, "seed": int(seed),
        "origin": {k: d.u(f"origin.{k}") for k in ("latitude_deg", "longitude_deg", "altitude_m")},
        "road": road,
        "surface": _surface(d, kinds),
        "lighting": _lighting(d),
        "cameras": {name: _camera(d) for name in camera_names},
        "traffic": traffic,
        "drive": {"speed_mps": d.u("drive.speed_mps"), "speed_variation_mps": d.u("drive.speed_variation_mps"),
                  "start_s_m": RANGES["drive.start_s_m"][0], "ego_lane": ego, "default_seconds": DEFAULT_SECONDS},
        "gnss": {"quality": "rtk"},
    }
    data["description"] = describe(data, kinds)
    return Scenario.model_validate(data)


def describe(data: dict, kinds: dict[str, str]) -> str:
    """One line naming what makes a drawn world what it is."""
    road, surface, light, traffic = data["road"], data["surface"], data["lighting"], data["traffic"]
    grades = [p["value"] for p in road["grade"]]
    return (f"random world {data['seed']}: {road['lanes']} lanes of {road['lane_width_m']:.2f} m; {kinds['paint']} "
            f"markings {road['marking_width_m']:.2f} m, dashes {kinds['dashes']}, contrast "
            f"{surface['paint_contrast']:.2f}, {100 * surface['paint_missing']:.0f} % worn away; {kinds['kerb']} "
            f"kerbs {100 * road['curb_height_m']:.0f} cm; grades {100 * min(grades):+.1f}..{100 * max(grades):+.1f} %, "
            f"crossfall {100 * road['crossfall']:.1f} %; asphalt {surface['asphalt_rgb'][1]:.2f}; sun "
            f"{light['sun_elevation_deg']:.0f} deg, {light['trees_per_100m']:.0f} trees / 100 m; "
            f"{traffic['moving_cars']} moving cars, {traffic['parked_cars_per_100m']:.0f} parked / 100 m")


def scenario_for(name_or_path: str | Path, seed: int | None, camera_names: Sequence[str]) -> Scenario:
    """`random` draws the world of `seed` (0 if none); any other name or path is a scenario file."""
    if str(name_or_path) == RANDOM:
        return draw_scenario(0 if seed is None else seed, camera_names)
    return load_scenario(name_or_path)
