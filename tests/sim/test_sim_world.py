"""The simulator's road world: scenarios validate, the world is deterministic from its seed, and the
ground-truth grids hold the road's geometry (crown, curbs, grades) and all five map classes."""

import numpy as np
import pytest

from daemon.spine.config import ConfigError
from daemon.spine.semantic_classes import SemanticClass
from sim.world.road_atlas import lane_boundaries
from sim.world.road_world import (
    GT_RES_M,
    NO_CLASS,
    build_centreline,
    build_world,
    ground_truth_grids,
    height_st,
    road_coordinates,
    road_point,
    surface_height,
)
from sim.world.scenarios import Scenario, load_scenario, scenario_names


@pytest.fixture(scope="module")
def city():
    return build_world(load_scenario("city"))


def test_named_scenarios_load_and_bad_ones_are_refused(tmp_path):
    assert {"city", "ramp", "night"} <= set(scenario_names())
    for name in ("city", "ramp", "night"):
        sc = load_scenario(name)
        assert sc.max_seconds() >= sc.drive.default_seconds
        assert 2 <= sc.road.lanes <= 4
    data = load_scenario("city").model_dump()
    data["drive"]["ego_lane"] = 0  # a parking lane
    with pytest.raises(ValueError, match="parking lane"):
        Scenario.model_validate(data)
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\norigin: {latitude_deg: 1, longitude_deg: 2}\nroad: {length_m: 300, lanes: 9}\n")
    with pytest.raises(ConfigError, match="lanes"):
        load_scenario(bad)


def test_ramp_has_a_steep_grade_over_60_m_and_the_city_is_flat_ish():
    ramp = build_centreline(load_scenario("ramp").road)
    steep = ramp.s[ramp.grade >= 0.08]
    assert 60 <= steep.max() - steep.min() <= 90
    assert ramp.grade.max() <= 0.10
    rise = np.interp(steep.max(), ramp.s, ramp.z) - np.interp(steep.min(), ramp.s, ramp.z)
    assert rise / (steep.max() - steep.min()) == pytest.approx(0.09, abs=0.01)
    city = build_centreline(load_scenario("city").road)
    assert np.abs(city.grade).max() <= 0.03
    assert city.grade.min() < -0.01 and city.grade.max() > 0.01  # a crest and a sag


def test_world_is_deterministic_from_the_seed(city):
    again = build_world(load_scenario("city"))
    other = build_world(load_scenario("city"), seed=12345)
    assert np.array_equal(city.atlas.albedo, again.atlas.albedo)
    assert np.array_equal(city.atlas.semantic, again.atlas.semantic)
    assert not np.array_equal(city.atlas.albedo, other.atlas.albedo)


def test_road_coordinates_round_trip(city):
    s = np.array([30.0, 120.0, 250.0, 333.3])
    t = np.array([-5.0, 0.0, 3.3, 7.0])
    xy = road_point(city, s, t).astype(np.float32)
    s2, t2 = road_coordinates(city, xy[:, 0], xy[:, 1])
    assert np.abs(s2 - s).max() < 0.01 and np.abs(t2 - t).max() < 0.01


def test_ground_truth_holds_crown_curbs_and_the_five_classes(city):
    sc = city.scenario
    gt = ground_truth_grids(city, (100.0, 140.0))
    assert gt.resolution == GT_RES_M
    present = set(np.unique(gt.semantic)) - {NO_CLASS}
    assert present == {int(c) for c in (SemanticClass.ROAD, SemanticClass.LANE_MARKING, SemanticClass.CURB,
                                        SemanticClass.MANHOLE, SemanticClass.BACKGROUND)}

    def cell(s, t):
        x, y = road_point(city, np.array([s]), np.array([t]))[0]
        j = int((x - gt.origin_xy[0]) / gt.resolution)
        i = int((y - gt.origin_xy[1]) / gt.resolution)
        return gt.elevation[i, j], gt.semantic[i, j]

    w = sc.road.road_half_width_m
    crown, _ = cell(120.0, 0.0)
    gutter, gutter_class = cell(120.0, -(w - 0.1))
    walk, walk_class = cell(120.0, -(w + 0.6))
    curb, curb_class = cell(120.0, -(w + 0.1))
    assert crown - gutter == pytest.approx(sc.road.crossfall * (w - 0.1), abs=0.01)
    assert walk - gutter == pytest.approx(sc.road.curb_height_m, abs=0.03)
    assert (gutter_class, curb_class, walk_class) == (SemanticClass.ROAD, SemanticClass.CURB,
                                                      SemanticClass.BACKGROUND)
    # The solid right edge line is painted where the lane boundary is.
    _, edge_class = cell(121.0, lane_boundaries(sc.road)[0])
    assert edge_class == SemanticClass.LANE_MARKING
    # The grid's elevation is the surface's height (to the 1/32-cell interpolation of the lookups).
    rows, cols = np.nonzero(np.isfinite(gt.elevation))
    pick = np.random.default_rng(0).choice(len(rows), 2000, replace=False)
    x = gt.origin_xy[0] + (cols[pick] + 0.5) * gt.resolution
    y = gt.origin_xy[1] + (rows[pick] + 0.5) * gt.resolution
    s, t = road_coordinates(city, x.astype(np.float32), y.astype(np.float32))
    smooth = np.abs(np.abs(t) - w) > 0.1  # away from the curb faces
    exact = height_st(city, s.astype(np.float64), t.astype(np.float64))
    assert np.abs(gt.elevation[rows[pick], cols[pick]] - exact)[smooth].max() < 0.005
    assert np.abs(surface_height(city, x.astype(np.float32), y.astype(np.float32)) - exact)[smooth].max() < 0.005
