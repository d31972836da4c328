"""Random worlds (`roadlog simulate --scenario random --seed N`): every drawn parameter stays in the range
random_world.RANGES states and the draws spread over it; two seeds draw different worlds (parameters and
rendered frames), one seed the same drive byte for byte, also read back from its recorded YAML; the named
scenarios are the worlds they were before the surface, shadows and camera responses became parameters."""

from __future__ import annotations

import hashlib
import json
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from daemon.log_format.reader import read_log, read_metadata
from daemon.spine.config import ConfigError, load_config
from daemon.spine.topics import camera_topic, mask_topic
from sim.drive_log import main as simulate_main
from sim.sensors.camera_renderer import camera_rig, render_view
from sim.world.random_world import DASH_PATTERNS_M, KERBS, RANGES, draw_scenario
from sim.world.road_atlas import palette, texture_strength
from sim.world.road_world import build_world
from sim.world.scenarios import Scenario, SurfaceSpec, load_scenario, scenario_names, with_camera_response
from sim.world.scene import build_scene
from sim.world.tree_shadows import tree_shadow

CONFIG = load_config(Path(__file__).resolve().parents[2] / "configs" / "sim.yaml")
CAMERAS = [cam.name for cam in CONFIG.sensors.cameras]
# Leaves a random world does not draw: the same in every world (or set by what was drawn: the ego lane).
NOT_DRAWN = {"name", "description", "seed", "start_utc", "lighting.mode", "lighting.headlight",
             "lighting.headlight_half_angle_deg", "gnss.quality", "drive.ego_lane", "traffic.parking_lanes[]"}
SEEDS = range(300)


def _leaves(value, path: str = ""):
    """(range key, value) of every leaf: list items as `[]`, camera names as `*`, colour channels under their colour."""
    if isinstance(value, dict):
        for k, v in value.items():
            key = "*" if path == "cameras" else k
            yield from _leaves(v, f"{path}.{key}" if path else key)
    elif isinstance(value, list):
        channels = path.endswith("_rgb") or path.endswith("white_balance")
        for v in value:
            yield from _leaves(v, path if channels else f"{path}[]")
    else:
        yield path, value


@pytest.fixture(scope="module")
def drawn() -> dict[str, list]:
    values = defaultdict(list)
    for seed in SEEDS:
        for key, value in _leaves(draw_scenario(seed, CAMERAS).model_dump(mode="json")):
            values[key].append(value)
    return values


def test_every_drawn_parameter_stays_in_its_stated_range(drawn):
    numeric = {k: v for k, v in drawn.items() if k not in NOT_DRAWN and k != "surface.curb_stripe_rgb"
               and k != "traffic.lead_car_gap_m"}
    unstated = sorted(set(numeric) - set(RANGES))
    assert not unstated, f"drawn without a stated range: {unstated}"
    for key, values in numeric.items():
        lo, hi = RANGES[key]
        assert all(lo <= v <= hi for v in values), (key, min(values), max(values), (lo, hi))
    for key in ("surface.curb_stripe_rgb", "traffic.lead_car_gap_m"):  # None in some worlds
        lo, hi = RANGES[key]
        present = [v for v in drawn[key] if v is not None]
        assert present and len(present) < len(drawn[key]), key
        assert all(lo <= v <= hi for v in present), key
    # every world validates as a scenario with the road it was drawn for
    assert all(len(drawn[k]) >= len(SEEDS) for k in ("road.lane_width_m", "lighting.sun_elevation_deg"))


def test_draws_spread_over_their_ranges_and_every_choice_occurs(drawn):
    uniform = ("road.lane_width_m", "road.marking_width_m", "road.curb_height_m", "road.crossfall",
               "surface.paint_contrast", "lighting.sun_elevation_deg", "lighting.sun_azimuth_deg", "lighting.exposure",
               "cameras.*.gain", "cameras.*.gamma", "cameras.*.saturation", "drive.speed_mps")
    for key in uniform:
        lo, hi = RANGES[key]
        values = np.array(drawn[key], float)
        assert values.min() < lo + 0.05 * (hi - lo) and values.max() > hi - 0.05 * (hi - lo), key
    grades = np.array(drawn["road.grade[].value"])
    assert np.abs(grades).max() > 0.075 and (np.abs(grades) < 0.02).mean() > 0.1  # steep and flat stretches
    assert set(zip(drawn["road.dash_length_m"], drawn["road.dash_gap_m"], strict=True)) == set(DASH_PATTERNS_M.values())
    assert set(drawn["road.lanes"]) == {2, 3, 4}
    kerb_texture = np.array(drawn["surface.curb_texture"])
    assert (kerb_texture > 0.18).any() and (kerb_texture < 0.14).any()  # granite and concrete or painted
    stripes = sum(v is not None for v in drawn["surface.curb_stripe_rgb"]) / 3 / len(SEEDS)  # 3 channels a world
    assert 0.2 < stripes < 0.5 and len(KERBS) == 3  # one kerb kind of three is painted red and white
    trees = np.array(drawn["lighting.trees_per_100m"])
    assert 0.25 < (trees == 0).mean() < 0.55 and trees.max() > 12
    missing = np.array(drawn["surface.paint_missing"])
    assert (missing == 0).mean() > 0.2 and missing.max() > 0.3
    paint_blue = np.array(drawn["surface.paint_rgb"]).reshape(len(SEEDS), 3)[:, 2]
    assert 0.1 < (paint_blue < 0.3).mean() < 0.4  # yellow paint in about a quarter of the worlds
    assert set(drawn["traffic.parked_cars_per_100m"]) > {0.0} and max(drawn["traffic.moving_cars"]) == 30


def test_print_scenario_draws_one_world_per_seed(capsys):
    def printed(*args: str) -> str:
        assert simulate_main(["--scenario", "random", *args, "--print-scenario"]) == 0
        return capsys.readouterr().out

    one, again, two = printed("--seed", "1"), printed("--seed", "1"), printed("--seed", "2")
    assert one == again and one != two
    world = Scenario.model_validate(yaml.safe_load(one))
    assert world == draw_scenario(1, CAMERAS) and world.seed == 1 and world.name == "random"
    assert set(world.cameras) == set(CAMERAS)
    other = Scenario.model_validate(yaml.safe_load(two))
    sections = ["road", "surface", "lighting", "cameras", "traffic"]
    assert [k for k in sections if getattr(world, k) != getattr(other, k)] == sections
    assert printed() == printed("--seed", "0")  # random without a seed is world 0


def test_two_seeds_render_different_frames_and_a_camera_response_it_was_given():
    views = []
    for seed in (3, 4):
        scene = build_scene(draw_scenario(seed, CAMERAS), CONFIG, 1.0)
        cam = scene.config.sensors.cameras[1]
        assert cam.photometry == scene.scenario.cameras[cam.name]  # the world's response, not the car config's
        assert cam.photometry != CONFIG.sensors.cameras[1].photometry
        rig = camera_rig(cam)
        views.append(render_view(scene, rig, 0.5))
        assert np.array_equal(views[-1].radiance, render_view(scene, rig, 0.5).radiance)
    a, b = views
    assert np.abs(a.radiance - b.radiance).mean() > 0.01
    assert not np.array_equal(a.labels, b.labels)


def test_camera_responses_for_cameras_the_car_lacks_are_refused():
    world = draw_scenario(0, [*CAMERAS, "rear"])
    with pytest.raises(ConfigError, match="rear"):
        with_camera_response(CONFIG, world)


def test_shadows_painted_kerbs_and_worn_paint_reach_the_surface():
    city = load_scenario("city")
    base = city.model_copy(update={"lighting": city.lighting.model_copy(update={
        "sun_elevation_deg": 30.0, "sun_azimuth_deg": 180.0})})  # shadows across the road
    trees = base.model_copy(update={"lighting": base.lighting.model_copy(update={"trees_per_100m": 10.0})})
    scene = build_scene(trees, CONFIG, 1.0)
    shadow = tree_shadow(scene.world, scene.sun_direction, np.random.default_rng([scene.seed, 11]))
    assert shadow is not None and 0.005 < (shadow > 0.5).mean() < 0.3
    plain = build_scene(base, CONFIG, 1.0)
    assert tree_shadow(plain.world, plain.sun_direction, np.random.default_rng(0)) is None
    assert np.array_equal(plain.world.atlas.albedo, scene.world.atlas.albedo)  # shadows are light, not paint
    sunny, shaded = shadow == 0, (shadow > 0.5) & (scene.world.atlas.semantic == 0)
    assert np.array_equal(scene.lit_atlas[sunny], plain.lit_atlas[sunny])
    assert shaded.mean() > 0.005  # some fall on the road, where the ground then gets about the ambient light only
    lit, unlit = plain.lit_atlas[shaded].astype(float).mean(), scene.lit_atlas[shaded].astype(float).mean()
    ambient, sun = base.lighting.ambient, base.lighting.sun
    assert unlit / lit < (ambient + 0.5 * sun * 0.5) / (ambient + sun * 0.5)

    worn_surface = base.surface.model_copy(update={"paint_missing": 0.3, "curb_stripe_rgb": (0.45, 0.06, 0.05)})
    worn = build_world(city.model_copy(update={"surface": worn_surface})).atlas
    fresh = plain.world.atlas  # the sun does not change the paint
    marking = 1
    kept = (worn.semantic == marking).sum() / (fresh.semantic == marking).sum()
    assert kept == pytest.approx(0.7, abs=0.02)  # 30 % of the paint worn away: road in the truth too
    rgb = worn.albedo.astype(np.int16)
    red = (rgb[..., 0] > 3 * rgb[..., 1]) & (worn.semantic == 2)
    assert 0.3 < red.sum() / (worn.semantic == 2).sum() < 0.6  # every other kerb block red


def test_the_named_scenarios_keep_the_worlds_they_had():
    # The surface's defaults are the values the atlas had built in.
    old_palette = np.array([[0.125, 0.125, 0.13], [0.075, 0.075, 0.08], [0.18, 0.175, 0.17], [0.70, 0.70, 0.66],
                            [0.36, 0.35, 0.33], [0.30, 0.26, 0.24], [0.09, 0.15, 0.05], [0.10, 0.095, 0.09]],
                           np.float32)
    assert np.array_equal(palette(SurfaceSpec())[:8], old_palette)
    old_texture = np.array([0.16, 0.12, 0.14, 0.10, 0.10, 0.12, 0.35, 0.10], np.float32)
    assert np.array_equal(texture_strength(SurfaceSpec())[:8], old_texture)
    for name in scenario_names():
        sc = load_scenario(name)
        assert sc.surface == SurfaceSpec() and not sc.cameras and sc.lighting.trees_per_100m == 0, name
        assert with_camera_response(CONFIG, sc) is CONFIG


def _digest(*arrays: np.ndarray | bytes) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(a if isinstance(a, bytes) else np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


# The session's 5 s city drive (seed 3) as the simulator made it before the random worlds (checked then: a city
# drive of 8 s, seed 12, gave a byte-identical log and truth before and after). If a change to the simulator means
# to change the named scenarios' worlds, say so in its commit and update these. The truth and the masks (PNG,
# lossless) are compared decoded, bit for bit; the camera frames are JPEG, whose bytes change with the OpenCV
# build (5.1.0 encodes other bytes than the 4.x/5.0 this digest was first taken with), so they are compared by
# count and by the mean and spread of their decoded pixels.
CITY_DRIVE_DIGESTS = {"truth": "0fe9a5f1fe957672", "front_wide_masks": "886d6771b14df0cf"}
CITY_FRONT_WIDE_FRAMES = {"count": 50, "mean": 148.771, "std": 59.977}  # decoded 8-bit pixels, every channel


def test_the_city_drive_is_the_one_it_was(city_drive):
    gt = np.load(city_drive.with_name("city.gt.npz"))
    assert "scenario_yaml" not in gt.files  # a named scenario is its file
    assert "scenario_yaml" not in read_metadata(city_drive)["roadlog"]
    truth = _digest(gt["elevation"], gt["semantic"], gt["albedo"], gt["lidar_points_enu"])
    records = list(read_log([city_drive]))
    masks = _digest(*(cv2.imdecode(np.frombuffer(bytes(r.message.data), np.uint8), cv2.IMREAD_UNCHANGED)
                      for r in records if r.topic == mask_topic("front_wide")))
    assert {"truth": truth, "front_wide_masks": masks} == CITY_DRIVE_DIGESTS
    frames = np.stack([cv2.imdecode(np.frombuffer(bytes(r.message.data), np.uint8), cv2.IMREAD_COLOR)
                       for r in records if r.topic == camera_topic("front_wide")]).astype(np.float64)
    assert len(frames) == CITY_FRONT_WIDE_FRAMES["count"]
    assert frames.mean() == pytest.approx(CITY_FRONT_WIDE_FRAMES["mean"], abs=0.2)
    assert frames.std() == pytest.approx(CITY_FRONT_WIDE_FRAMES["std"], abs=0.2)


def test_a_random_drive_is_reproduced_from_its_seed_and_from_its_recorded_world(tmp_path, capsys):
    first, second = tmp_path / "a" / "drive.mcap", tmp_path / "b" / "drive.mcap"  # the log names its truth file
    first.parent.mkdir()
    second.parent.mkdir()
    assert simulate_main(["--scenario", "random", "--seed", "7", "--seconds", "0.5", "--out", str(first)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["scenario"] == "random" and summary["world"]["seed"] == 7
    recorded = read_metadata(first)["roadlog"]["scenario_yaml"]
    assert str(np.load(first.with_name("drive.gt.npz"))["scenario_yaml"]) == recorded
    world = tmp_path / "world7.yaml"
    world.write_text(recorded)
    assert Scenario.model_validate(yaml.safe_load(recorded)) == draw_scenario(7, CAMERAS)
    assert simulate_main(["--scenario", str(world), "--seconds", "0.5", "--out", str(second)]) == 0
    assert first.read_bytes() == second.read_bytes()
    assert first.with_name("drive.gt.npz").read_bytes() == second.with_name("drive.gt.npz").read_bytes()
