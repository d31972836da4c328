"""Named simulator scenarios (configs/scenarios/NAME.yaml): the road, its surface's materials, traffic, light,
the cameras' response and GNSS quality of one simulated drive, validated once by a pydantic schema. The
ranges a random world draws each value from are sim/world/random_world.py's (docs/simulator.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from daemon.spine.config import CameraPhotometry, CarConfig, ConfigError

SCENARIO_DIR = Path(__file__).resolve().parents[2] / "configs" / "scenarios"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Rgb = tuple[float, float, float]  # linear RGB albedo (reflectance), each channel in [0, 1]


class ProfilePoint(_Strict):
    """A control point of a profile along the road: at arc length s_m the value is `value`."""

    s_m: float = Field(ge=0)
    value: float


class RoadSpec(_Strict):
    length_m: float = Field(gt=50, le=3000)
    heading_deg: float = 0.0  # direction of the road's start, counter-clockwise from east
    lanes: int = Field(ge=2, le=4)
    lane_width_m: float = Field(3.25, ge=2.5, le=4.5)
    crossfall: float = Field(0.025, ge=0, le=0.05)  # crown slope from the centre line to the gutters
    curb_height_m: float = Field(0.15, ge=0, le=0.3)
    gutter_m: float = Field(0.3, ge=0, le=1.0)  # road surface between the edge line and the curb
    sidewalk_width_m: float = Field(3.0, ge=0.5, le=8)
    marking_width_m: float = Field(0.15, gt=0.05, le=0.4)
    dash_length_m: float = Field(3.0, gt=0.5)
    dash_gap_m: float = Field(6.0, gt=0.5)
    arrow_spacing_m: float = Field(60.0, gt=10)
    manhole_spacing_m: float = Field(30.0, gt=5)
    patches_per_100m: float = Field(4.0, ge=0)
    cracks_per_100m: float = Field(30.0, ge=0)
    stains_per_100m: float = Field(8.0, ge=0)
    grade: list[ProfilePoint] = [ProfilePoint(s_m=0, value=0.0)]  # rise / run; smoothly interpolated
    curvature: list[ProfilePoint] = [ProfilePoint(s_m=0, value=0.0)]  # 1/m, positive turning left

    @model_validator(mode="after")
    def _profiles(self) -> RoadSpec:
        for name in ("grade", "curvature"):
            points = getattr(self, name)
            s = [p.s_m for p in points]
            if not points or s != sorted(s) or len(set(s)) != len(s):
                raise ValueError(f"{name}: control points must be given with strictly increasing s_m")
        if any(abs(p.value) > 0.12 for p in self.grade):
            raise ValueError("grade: |grade| must stay at or below 0.12 (12 %)")
        if any(abs(p.value) > 1 / 30 for p in self.curvature):
            raise ValueError("curvature: radius must be at least 30 m (|curvature| <= 1/30)")
        return self

    @property
    def road_half_width_m(self) -> float:
        """Centre line to curb face."""
        return self.lanes * self.lane_width_m / 2 + self.gutter_m


def _albedo(rgb: Rgb) -> Rgb:
    if not all(0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"albedo {rgb}: every channel must lie in [0, 1]")
    return rgb


class SurfaceSpec(_Strict):
    """The painted surface's materials: linear RGB albedo, texture strength (relative albedo variation) and
    grain. The defaults are the city's (the values the atlas had built in)."""

    asphalt_rgb: Rgb = (0.125, 0.125, 0.13)
    asphalt_texture: float = Field(0.16, ge=0, le=0.5)
    texture_fine_m: float = Field(0.4, ge=0.05, le=2.0)  # feature size of the fine grain noise
    texture_coarse_m: float = Field(4.0, ge=0.5, le=20.0)  # ... and of the large-scale blotches
    patch_dark_rgb: Rgb = (0.075, 0.075, 0.08)  # fresh patches
    patch_light_rgb: Rgb = (0.18, 0.175, 0.17)  # worn patches
    paint_rgb: Rgb = (0.70, 0.70, 0.66)  # markings and arrows
    paint_contrast: float = Field(1.0, ge=0.2, le=1.0)  # 1: fresh paint; less: faded towards the asphalt
    paint_missing: float = Field(0.0, ge=0, le=0.6)  # fraction of the paint worn away (road there, in the truth too)
    paint_wear_m: float = Field(0.3, ge=0.05, le=2.0)  # size of the worn-away fragments
    curb_rgb: Rgb = (0.36, 0.35, 0.33)
    curb_texture: float = Field(0.10, ge=0, le=0.5)
    curb_stripe_rgb: Rgb | None = None  # a second colour in alternating blocks (red/white painted kerbs)
    curb_stripe_m: float = Field(1.0, ge=0.2, le=5.0)  # length of each block
    sidewalk_rgb: Rgb = (0.30, 0.26, 0.24)  # paving stones
    verge_rgb: Rgb = (0.09, 0.15, 0.05)  # grass
    manhole_rgb: Rgb = (0.10, 0.095, 0.09)  # cast iron

    @model_validator(mode="after")
    def _colours(self) -> SurfaceSpec:
        for name in type(self).model_fields:
            if name.endswith("_rgb") and getattr(self, name) is not None:
                _albedo(getattr(self, name))
        return self


class TrafficSpec(_Strict):
    parking_lanes: list[int] = []  # lane indices (0 = rightmost) holding parked cars
    parked_cars_per_100m: float = Field(0.0, ge=0, le=20)
    moving_cars: int = Field(0, ge=0, le=60)
    lead_car_gap_m: float | None = Field(None, gt=8)  # a car ahead in the ego lane at the ego's speed


class LightingSpec(_Strict):
    mode: Literal["day", "night"] = "day"
    ambient: float = Field(0.45, ge=0, le=2)
    sun: float = Field(0.7, ge=0, le=3)
    sun_elevation_deg: float = Field(45.0, ge=0, le=90)
    sun_azimuth_deg: float = 135.0
    headlight: float = Field(0.0, ge=0)  # illuminance at 10 m on the headlight axis (night)
    headlight_half_angle_deg: float = Field(18.0, gt=1, le=60)
    exposure: float = Field(1.0, gt=0)
    noise_scale: float = Field(1.0, ge=0)  # multiplies every camera's noise_sigma (sensor gain noise)
    fog_distance_m: float = Field(250.0, gt=10)
    # Roadside trees beyond the sidewalks, both sides: only their shadows are drawn (on the road, by day).
    trees_per_100m: float = Field(0.0, ge=0, le=30)
    tree_height_m: float = Field(8.0, gt=1, le=30)  # crown centre above the ground (each tree +-25 %)
    tree_crown_radius_m: float = Field(2.5, gt=0.3, le=8)  # (each tree +-30 %)
    tree_setback_m: float = Field(1.0, ge=0, le=10)  # from the sidewalk's outer edge to the trunk


class DriveSpec(_Strict):
    speed_mps: float = Field(10.0, gt=0, le=40)
    speed_variation_mps: float = Field(0.5, ge=0)
    start_s_m: float = Field(20.0, ge=5)
    ego_lane: int = Field(0, ge=0)
    default_seconds: float = Field(30.0, gt=0)


class GnssSpec(_Strict):
    quality: Literal["rtk", "metre"] = "rtk"


class OriginSpec(_Strict):
    latitude_deg: float = Field(ge=-85, le=85)
    longitude_deg: float = Field(ge=-180, le=180)
    altitude_m: float = 0.0


class Scenario(_Strict):
    name: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    description: str = ""
    seed: int = 0
    start_utc: str = "2026-06-01T10:00:00Z"
    origin: OriginSpec
    road: RoadSpec
    traffic: TrafficSpec = TrafficSpec()
    lighting: LightingSpec = LightingSpec()
    drive: DriveSpec = DriveSpec()
    gnss: GnssSpec = GnssSpec()
    surface: SurfaceSpec = SurfaceSpec()
    # Per-camera photometric response by camera name, in place of the car config's `photometry`.
    cameras: dict[str, CameraPhotometry] = {}

    @model_validator(mode="after")
    def _lanes(self) -> Scenario:
        lanes = self.road.lanes
        if self.drive.ego_lane >= lanes:
            raise ValueError(f"drive.ego_lane must be below road.lanes={lanes}")
        if any(k < 0 or k >= lanes for k in self.traffic.parking_lanes):
            raise ValueError(f"traffic.parking_lanes must name lanes 0..{lanes - 1}")
        if self.drive.ego_lane in self.traffic.parking_lanes:
            raise ValueError("the ego lane cannot be a parking lane")
        if self.drive.ego_lane >= (lanes + 1) // 2:
            raise ValueError("the ego lane must be one of the right-hand (forward) lanes")
        return self

    def max_seconds(self) -> float:
        """The longest drive the road allows (leaving 100 m of road ahead for the sensors to see)."""
        return (self.road.length_m - self.drive.start_s_m - 100.0) / (
            self.drive.speed_mps + self.drive.speed_variation_mps)


def with_camera_response(config: CarConfig, scenario: Scenario) -> CarConfig:
    """The car config with the scenario's per-camera photometric responses in place of its own (the same
    config when the scenario names none); a camera the car does not have is a ConfigError."""
    if not scenario.cameras:
        return config
    cameras = config.sensors.cameras
    unknown = sorted(set(scenario.cameras) - {cam.name for cam in cameras})
    if unknown:
        raise ConfigError(f"scenario {scenario.name}: cameras {', '.join(unknown)} are not in the car config "
                          f"(it has {', '.join(cam.name for cam in cameras)})")
    cameras = [cam.model_copy(update={"photometry": scenario.cameras[cam.name]}) if cam.name in scenario.cameras
               else cam for cam in cameras]
    return config.model_copy(update={"sensors": config.sensors.model_copy(update={"cameras": cameras})})


def scenario_names() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A scenario by name (configs/scenarios/NAME.yaml) or path; a bad file raises ConfigError."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = SCENARIO_DIR / f"{name_or_path}.yaml"
        if not path.exists():
            raise ConfigError(f"unknown scenario {name_or_path!r} (choose from {', '.join(scenario_names())})")
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read scenario: {exc}") from None
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        lines = [f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()]
        raise ConfigError(f"{path}: invalid scenario:\n  " + "\n  ".join(lines)) from None
