"""`roadlog fleet reconstruct` as a user runs it (a subprocess, a local Ray of its own) on the session's short
city drive: every window fitted once into the tile store and journalled, progress for the job on stderr, a merged
map on the UTM grid; run again on the same folder it fits nothing; a window made to fail is retried, reported and
journalled failed while the others are done (exit 1), and the next run fits only that window."""

from __future__ import annotations

import importlib.util
import json
import os

import numpy as np
import pytest
import rasterio

from mapping.fleet.drive_windows import FAIL_WINDOWS_ENV, drive_id
from mapping.fleet.fleet_journal import FleetJournal
from mapping.fleet.tile_store import TileStore
from tests.roadlog_cli import roadlog

# a coarse, short-windowed mapper: windows of 40 m every 20 m on the 5 s drive, each fitted in seconds
SMALL_MAPPER = """mapper:
  mesh: {side_m: 0.25, corridor_half_width_m: 10.0}
  windows: {before_m: 20.0, after_m: 20.0}
  inputs: {keyframe_spacing_m: 2.0, lidar_every_n_scans: 4}
  fast_fit: {elevation_min_steps: 40, lidar_detail_passes: 2}
"""


def _fleet(tmp_path, log, out, env_extra=None):
    mapper = tmp_path / "mapper.yaml"
    mapper.write_text(SMALL_MAPPER)
    env = {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM", "INVOCATION_ID", FAIL_WINDOWS_ENV)}
    env.update(env_extra or {})
    return roadlog("fleet", "reconstruct", str(log), "--out", str(out), "--workers", "1", "--retries", "1",
                   "--mapper", str(mapper), timeout=900, env=env)


@pytest.mark.slow
@pytest.mark.timeout(2400)  # three runs of the command, each starting its own Ray, on a loaded 2-core machine
def test_fleet_reconstruct_is_resumable_idempotent_and_survives_a_failing_window(city_drive, tmp_path):
    pytest.importorskip("ray", reason="Ray, the fleet's optional dependency, is not installed: pip install '.[fleet]'")
    out = tmp_path / "job"
    name = drive_id([city_drive])
    first = _fleet(tmp_path, city_drive, out, {FAIL_WINDOWS_ENV: f"{city_drive.stem}:1"})
    assert first.returncode == 1, first.stderr[-3000:]
    summary = json.loads(first.stdout.strip().splitlines()[-1])
    n = summary["windows"]  # 40 m windows every 20 m over the drive's ~50 m
    assert n >= 3 and summary["windows_done"] == n - 1 and summary["windows_failed"] == 1
    (failure,) = summary["failures"]
    assert failure["drive"] == name and failure["window"] == 1 and len(failure["errors"]) == 2  # tried twice
    assert "injected failure" in failure["errors"][0]
    assert f"windows done {n - 1}, failed 1, of {n}" in first.stderr  # progress of the whole job
    journal = FleetJournal(out)
    assert journal.window(name, 1)["status"] == "failed"
    assert all(journal.done(name, k) for k in range(n) if k != 1)
    store = TileStore(out)
    tiles = store.tiles()
    assert tiles and all(str(t).startswith("32N_") for t in tiles)  # Munich: UTM zone 32 north
    windows = {i.window for t in tiles for i in store.contributions(t)}
    assert windows == set(range(n)) - {1}  # the failed window contributed nothing
    done0 = journal.window(name, 0)
    assert sorted(done0["tiles"]) == sorted(str(t) for t in tiles if any(
        i.window == 0 for i in store.contributions(t)))
    stamps = {p: p.stat().st_mtime_ns for p in (out / "tiles").rglob("*.w0.npz")}
    # the map: merged on the UTM grid, heights ellipsoidal (the city lies at 520 m)
    with rasterio.open(out / "map" / "bev_elevation.tif") as tif:
        assert tif.crs.to_epsg() == 32632
        z = tif.read(1)
    assert 515 < np.nanmedian(z) < 525

    second = _fleet(tmp_path, city_drive, out)  # no failure now: only window 1 is fitted
    assert second.returncode == 0, second.stderr[-3000:]
    again = json.loads(second.stdout.strip().splitlines()[-1])
    assert again["windows_fitted"] == 1 and again["windows_reused"] == n - 1 and again["windows_done"] == n
    assert {i.window for t in store.tiles() for i in store.contributions(t)} == set(range(n))
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items())  # window 0 not written again

    third = _fleet(tmp_path, city_drive, out)  # everything done: nothing read, nothing fitted
    assert third.returncode == 0, third.stderr[-3000:]
    done = json.loads(third.stdout.strip().splitlines()[-1])
    assert done["windows_fitted"] == 0 and done["windows_reused"] == n
    assert json.loads((out / "fleet.json").read_text())["drives"][0]["load_s"] is None  # the drive was not read


def test_fleet_refuses_bad_arguments_with_one_error_line(tmp_path):
    not_log = tmp_path / "x.mcap"
    not_log.write_text("no")
    result = roadlog("fleet", "reconstruct", str(not_log), "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "error:" in result.stderr
    assert roadlog("fleet", "rebuild").returncode == 2
    bad = tmp_path / "mapper.yaml"
    bad.write_text("mapper: {mesh: {side_m: -1}}\n")
    log = tmp_path / "log.mcap"
    from daemon.spine.config import load_config
    from tests.daemon_fixtures import REPO
    from tests.roadlog_cli import can_only_log

    can_only_log(log, load_config(REPO / "configs" / "sim.yaml"))
    result = roadlog("fleet", "reconstruct", str(log), "--out", str(tmp_path / "o"), "--mapper", str(bad))
    assert result.returncode == 2 and "mesh.side_m" in result.stderr


def test_without_ray_the_fleet_command_says_how_to_install_it_in_one_line(city_drive, tmp_path):
    if importlib.util.find_spec("ray") is not None:
        pytest.skip("Ray is installed here: the message for its absence cannot be seen")
    run = roadlog("fleet", "reconstruct", str(city_drive), "--out", str(tmp_path / "job"), timeout=120)
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert run.stderr.strip().splitlines()[-1].startswith("error: roadlog fleet needs Ray") and "[fleet]" in run.stderr
