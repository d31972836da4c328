"""Another visit of the same world (`roadlog simulate --visit N`, sim/world/revisit.py): the same road, paint and
truth; other traffic, light, noise and a GNSS offset the log's fixes carry; visit 0 is the plain drive."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from daemon.log_format.reader import read_log, read_metadata
from daemon.spine.config import load_config
from daemon.spine.local_frame import LocalFrame
from daemon.spine.topics import GNSS_FIX
from sim.drive_log import main as simulate_main
from sim.world.revisit import GNSS_OFFSET_H_M, GNSS_OFFSET_V_M, visit
from sim.world.scenarios import load_scenario
from sim.world.scene import build_scene

CONFIG = load_config(Path(__file__).resolve().parents[2] / "configs" / "sim.yaml")


def test_a_visit_keeps_the_world_and_changes_the_drive():
    sc = load_scenario("city")
    plain = visit(sc, sc.seed, 0)
    assert plain.scenario is sc and plain.drive_seed == sc.seed and plain.gnss_offset_enu_m == (0.0, 0.0, 0.0)
    second = visit(sc, sc.seed, 1)
    assert second == visit(sc, sc.seed, 1)  # deterministic
    assert second.drive_seed != sc.seed and second.scenario.road == sc.road and second.scenario.traffic == sc.traffic
    assert second.scenario.lighting.sun_azimuth_deg != sc.lighting.sun_azimuth_deg
    east, north, up = second.gnss_offset_enu_m
    assert 0 < np.hypot(east, north) <= GNSS_OFFSET_H_M and abs(up) <= GNSS_OFFSET_V_M
    a = build_scene(sc, CONFIG, 4.0, sc.seed, sc.seed)
    b = build_scene(second.scenario, CONFIG, 4.0, second.drive_seed, sc.seed)
    assert np.array_equal(a.world.atlas.albedo, b.world.atlas.albedo)  # the same road, paint and stains
    assert np.array_equal(a.world.height, b.world.height)
    assert not np.array_equal(a.traffic.s0, b.traffic.s0)  # other cars parked and moving
    assert not np.array_equal(a.lit_atlas, b.lit_atlas)  # other light


@pytest.mark.slow
def test_a_visits_log_has_the_worlds_truth_and_offset_fixes(tmp_path, capsys):
    first, second = tmp_path / "a" / "drive.mcap", tmp_path / "b" / "drive.mcap"
    first.parent.mkdir()
    second.parent.mkdir()
    args = ["--scenario", "city", "--seconds", "1", "--workers", "1"]
    assert simulate_main([*args, "--out", str(first)]) == 0
    assert simulate_main([*args, "--visit", "2", "--out", str(second)]) == 0
    capsys.readouterr()
    ta, tb = np.load(first.with_name("drive.gt.npz")), np.load(second.with_name("drive.gt.npz"))
    res = float(ta["grid_resolution_m"])
    shift = np.rint((tb["grid_origin_xy"] - ta["grid_origin_xy"]) / res).astype(int)  # both snapped to the grid
    di, dj = int(shift[1]), int(shift[0])
    rows = min(ta["elevation"].shape[0], tb["elevation"].shape[0] + di) - max(0, di)
    cols = min(ta["elevation"].shape[1], tb["elevation"].shape[1] + dj) - max(0, dj)
    a_cells = (slice(max(0, di), max(0, di) + rows), slice(max(0, dj), max(0, dj) + cols))
    b_cells = (slice(max(0, -di), max(0, -di) + rows), slice(max(0, -dj), max(0, -dj) + cols))
    assert rows > 500 and cols > 500  # the truths overlap where both drives went (their lengths differ a little)
    both = np.isfinite(ta["elevation"][a_cells]) & np.isfinite(tb["elevation"][b_cells])  # ends cut to each drive
    assert both.sum() > 0.8 * np.isfinite(ta["elevation"]).sum()
    for grid in ("elevation", "semantic", "albedo"):
        assert np.array_equal(ta[grid][a_cells][both], tb[grid][b_cells][both]), grid
    meta = read_metadata(second)["roadlog"]
    assert meta["visit"] == "2" and "scenario_yaml" in meta  # its light is not the named scenario's
    offset = np.array(json.loads(meta["gnss_offset_enu_m"]))
    assert np.allclose(offset, visit(load_scenario("city"), 11, 2).gnss_offset_enu_m)
    frame = LocalFrame(*(float(v) for v in ta["enu_origin_lat_lon_alt"]))

    def fix_error(path: Path, truth) -> np.ndarray:
        """The fixes' mean position less the truth's at their arrival (the lever arm and latency alike on both)."""
        fixes = [r.message for r in read_log([path], topics={GNSS_FIX})]
        enu = frame.geodetic_to_enu(np.array([f.latitude_deg for f in fixes]),
                                    np.array([f.longitude_deg for f in fixes]), np.array([f.altitude_m for f in fixes]))
        host = np.array([f.host_mono_ns for f in fixes], np.float64)
        t, pos = truth["trajectory_host_mono_ns"].astype(np.float64), truth["trajectory_position_enu"]
        return (enu - np.stack([np.interp(host, t, pos[:, k]) for k in range(3)], 1)).mean(0)

    assert np.linalg.norm(fix_error(second, tb) - fix_error(first, ta) - offset) < 0.05
