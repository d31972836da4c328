"""The live mapping worker: its spool, tiles, window schedule, and the real process on a replayed drive.

The end-to-end test (slow: 5-15 min on the shared 2-core machine, a window takes 20-150 s there)
runs `python -m mapping.live.mapping_worker` against the real bus, fed by `daemon.processes.replay` at the recorded
rate from a short simulated city drive, kills it with SIGKILL mid-drive, restarts it, stops it with
SIGTERM and checks the journal, tiles, previews and map.
"""

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from daemon.bus import pubsub
from daemon.log_format.reader import read_log
from daemon.processes.replay import replay
from daemon.spine.messages import CameraFrame, GnssFix
from daemon.spine.topics import (
    GNSS_FIX,
    LIDAR_IMU,
    LIDAR_PACKETS,
    WHEEL_SPEEDS,
    camera_topic,
    health_topic,
    topic_table,
)
from mapping.live import map_tiles
from mapping.live.final_map import FinalMapMetadata, map_semantics, write_final_map
from mapping.live.keyframe_spool import KeyframeSpool
from mapping.live.window_schedule import window_span, windows_ended, windows_for_drive
from mapping.live.worker_journal import JOURNAL_NAME, read_journal
from mapping.live.worker_loop import MappingWorker
from tests.daemon_fixtures import REPO, private_config
from tests.mapping.fed_worker import SMALL_WINDOWS, worker_fed


# ---- spool, tiles, schedule (odometry: test_replay_determinism.py) ------------------------------------
def test_spool_round_trip_survives_a_torn_tail_and_prunes_whole_chunks(tmp_path):
    config, _ = private_config(tmp_path)
    topics = topic_table(config)
    spool = KeyframeSpool(tmp_path / "spool", topics, chunk_s=1.0)
    sent = []
    for i in range(30):
        t = 1_000_000_000 + i * 100_000_000  # 10 Hz for 3 s: three chunks of 1.1 s
        fix = GnssFix(seq=i, sensor_time_ns=t, host_mono_ns=t, latitude_deg=48.0 + i * 1e-6, longitude_deg=11.0)
        frame = CameraFrame(seq=i, sensor_time_ns=t, host_mono_ns=t, camera="front_wide", data=bytes([i]) * 1000)
        spool.append(GNSS_FIX, fix, t)
        spool.append(camera_topic("front_wide"), frame, t)
        sent.append((fix, frame))
    spool.flush_close()
    assert len(spool.chunks) == 3
    with open(spool.chunks[-1].path, "ab") as f:
        f.write(b"\x05\x00\x10\x00")  # a record cut short by a crash
    again = KeyframeSpool(tmp_path / "spool", topics)
    got = list(again.read(0, 10**12, {GNSS_FIX, camera_topic("front_wide")}))
    assert again.torn_records >= 1
    assert [m.seq for _, t, m in got if t == GNSS_FIX] == list(range(30))
    frames = [m for _, t, m in got if t != GNSS_FIX]
    assert bytes(frames[7].data) == bytes([7]) * 1000 and frames[7].sensor_time_ns == sent[7][1].sensor_time_ns
    assert got[2][2].latitude_deg == sent[1][0].latitude_deg
    freed = again.prune_before(2_200_000_000)
    assert freed > 0 and again.chunks[0].last_ns >= 2_200_000_000
    assert [m.seq for _, _, m in again.read(0, 10**12, {GNSS_FIX})][0] > 0


def _raster(i0, j0, h, w, value, central):
    return map_tiles.WindowRaster(i0, j0, np.full((h, w), value, np.float32), np.full((h, w), int(value), np.uint8),
                                  {"cam": np.full((h, w, 3), int(value), np.uint8)}, np.asarray(central))


def test_tiles_the_central_stretch_overrides_and_margins_only_fill_gaps(tmp_path):
    folder, n = tmp_path / "tiles", 10
    central0 = np.zeros((5, 30), bool)
    central0[:, :15] = True
    map_tiles.write_window(folder, n, 0, _raster(-2, -5, 5, 30, 1.0, central0), ["cam"])  # crosses 6 tiles
    central1 = np.zeros((5, 30), bool)
    central1[:, 5:25] = True  # global columns 10..29
    map_tiles.write_window(folder, n, 1, _raster(-2, 5, 5, 30, 2.0, central1), ["cam"])
    map_tiles.write_window(folder, n, 2, _raster(-2, 0, 5, 40, 3.0, np.zeros((5, 40), bool)), ["cam"])
    mos = map_tiles.mosaic(folder, n, 0.1, ["cam"])
    assert mos.origin_xy == (-1.0, -1.0) and mos.resolution_m == 0.1
    row = mos.elevation[-2 + 10]  # global row 0
    col = lambda j: row[j + 10]  # noqa: E731
    assert col(-5) == 1 and col(9) == 1  # window 0's central stretch
    assert col(10) == 2 and col(29) == 2  # window 1's central stretch overrides window 0's margin
    assert col(0) == 1 and col(5) == 1  # later margins never replace a central stretch
    assert col(30) == 3 and col(34) == 3 and col(39) == 3  # a later margin replaces an earlier margin
    assert np.isnan(col(-6)) and np.isnan(col(-10)) and row.shape == (50,)  # tiles -1..3
    assert mos.rgb["cam"][-2 + 10, 20 + 10, 0] == 2 and mos.owner[-2 + 10, 35 + 10] == -3


def test_window_schedule_overlaps_by_half_and_covers_the_drive():
    assert window_span(0, 80, 80) == (0.0, 0.0, 80.0)
    assert window_span(3, 80, 80) == (240.0, 160.0, 320.0)
    assert windows_for_drive(50.0, 10, 10) == 6  # centres 0..50 m, each owning +-5 m
    assert windows_for_drive(1.0, 80, 80) == 1
    # windows end at 80, 160, 240, ... m: at 239 m windows 0 and 1 have ended, 2 has not
    assert windows_ended(0, 239.0, 80, 80) == 2 and windows_ended(0, 240.0, 80, 80) == 3
    assert windows_ended(1, 239.0, 80, 80) == 1 and windows_ended(5, 239.0, 80, 80) == 0


# ---- the real worker process on a replayed drive ---------------------------------------------------------
def _start_worker(config_path: Path, log: Path, *args: str, path_first: Path | None = None) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(p) for p in (path_first, REPO) if p))
    return subprocess.Popen([sys.executable, "-m", "mapping.live.mapping_worker", "--config", str(config_path), *args],
                            cwd=REPO, env=env, stdout=open(log, "ab"), stderr=subprocess.STDOUT)


def _windows(folder: Path) -> list[dict]:
    journal = read_journal(folder)
    return [] if journal is None else [w.to_json() for w in journal.windows]


def _wait_for(predicate, timeout_s: float, what: str, proc: subprocess.Popen | None = None):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"worker exited with {proc.returncode} while waiting for {what}")
        time.sleep(0.5)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_worker_maps_as_data_arrives_survives_kill_9_and_writes_the_final_map(city_drive, tmp_path):
    data = tmp_path / "data"
    config, config_path = private_config(tmp_path, mapper=SMALL_WINDOWS, recorder={"output_dir": str(data)})
    journal_path = data / "map"  # the journal's folder
    log = tmp_path / "worker.log"
    procs = []
    try:
        procs.append(_start_worker(config_path, log))
        player = threading.Thread(target=replay, args=(config, [city_drive]), kwargs={"rate": 1.0})
        player.start()
        health = pubsub.open_subscriber(config, health_topic("mapper"), wait_s=60)
        # windows are optimised while the drive's data arrives, with no end-of-drive signal
        _wait_for(lambda: len(_windows(journal_path)) >= 1, 600, "a window", procs[0])
        before_kill = _windows(journal_path)
        assert all(w["status"] == "done" for w in before_kill)
        _wait_for(lambda: health.latest() is not None and json.loads(health.latest().detail)["windows_done"] >= 1,
                  60, "health after the first window", procs[0])
        detail = json.loads(health.latest().detail)
        assert detail["distance_m"] > 10 and detail["spool_bytes"] > 0
        assert {"windows_pending", "mapped_until_m", "lag_m", "lag_s", "last_window_wall_s", "errors"} <= set(detail)
        for name in ("rgb", "semantics", "elevation"):
            assert (data / "map" / "previews" / f"{name}.png").stat().st_size > 0
        # kill -9 (mid-drive unless the machine is slow): the restart keeps every finished window and goes on
        # from the spool and the bus; a window whose data has all arrived runs without waiting for the end
        procs[0].kill()
        procs[0].wait()
        killed_ns = time.monotonic_ns()
        kept = _windows(journal_path)
        with open(journal_path / JOURNAL_NAME, "ab") as f:  # as if the kill had torn a line mid-write
            f.write(b'{"window": {"index": 99, "sta')
        procs.append(_start_worker(config_path, log))
        player.join()
        # it is up and handles SIGTERM: its own health, not the `starting` one sent before torch loads
        _wait_for(lambda: (m := health.latest()) is not None and m.host_mono_ns > killed_ns
                  and "starting" not in json.loads(m.detail), 300, "the restarted worker's health", procs[1])
        restarted = json.loads(health.latest().detail)
        assert restarted["errors"] >= 1 and "journal: 1 unreadable line" in restarted["last_error"]
        procs[1].send_signal(signal.SIGTERM)
        assert procs[1].wait(timeout=1200) == 0, log.read_text()[-3000:]
        final = json.loads(health.latest().detail)
        assert final["finished"] and final["bus_lost"] == 0  # the drive came at its real rate: nothing lost
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        pubsub.unlink_all(config)
    journal = read_journal(journal_path)
    windows = [w.to_json() for w in journal.windows]
    assert journal.finished and windows[:len(kept)] == kept and len(windows) > len(kept)
    assert journal.skipped_lines == 1
    assert [w["index"] for w in windows] == list(range(len(windows)))
    assert all(w["status"] == "done" for w in windows), [w.get("error") for w in windows]
    distance = journal.odometry_s[-1]
    assert 40 < distance < 60  # 5 s at 10 m/s
    assert len(windows) == windows_for_drive(distance, 10, 10)
    assert all(w["config"]["sha256"] == journal.header.config_sha256 for w in windows)
    assert all(w["seq"]["gnss/fix"][0] <= w["seq"]["gnss/fix"][1] and w["keyframes"] > 0 for w in windows)
    # the map grows along the trajectory: window boxes move away from the start, and the final map covers them
    centres = np.array([[(w["trajectory_xy_box"][0] + w["trajectory_xy_box"][2]) / 2,
                         (w["trajectory_xy_box"][1] + w["trajectory_xy_box"][3]) / 2] for w in windows])
    from_start = np.linalg.norm(centres - centres[0], axis=1)
    assert np.all(np.diff(from_start) > 0) and from_start[-1] > 30
    final = data / "map" / "final"
    meta = asdict(FinalMapMetadata.read(final))
    elevation = np.load(final / "bev_elevation.npy")
    res, (x0, y0) = meta["resolution_m"], meta["origin_xy"]
    for k, (cx, cy) in enumerate(centres):  # the road within ~4 m of each window's middle is mapped
        i, j = int(round((cy - y0) / res)), int(round((cx - x0) / res))
        covered = np.isfinite(elevation[i - 15:i + 16, j - 15:j + 16]).mean()
        assert covered > (0.3 if k == 0 else 0.75)  # the first one's middle is only 5 m from the start
    assert len(meta["windows"]) == len(windows)
    for name in ("bev_semantics.png", "bev_elevation.png", "bev_rgb_front_wide.png", "mesh.ply", "mesh.glb"):
        assert (final / name).stat().st_size > 0
    assert not (data / "map" / "spool").exists()


def test_rasters_written_a_row_of_tiles_at_a_time_equal_the_mosaic(tmp_path):
    folder, n = tmp_path / "tiles", 10
    central = np.ones((5, 30), bool)
    map_tiles.write_window(folder, n, 0, _raster(-2, -5, 5, 30, 1.0, central), ["cam"])
    map_tiles.write_window(folder, n, 1, _raster(23, 40, 5, 12, 2.0, np.ones((5, 12), bool)), ["cam"])  # far off
    for max_cells in (10**9, 900):  # full resolution, and subsampled by a stride
        mos = map_tiles.mosaic(folder, n, 0.1, ["cam"], max_cells=max_cells)
        paths = {"elevation": tmp_path / "e.npy", "labels": tmp_path / "l.npy"}
        grid = map_tiles.write_mosaic_npy(folder, n, 0.1, paths, max_cells=max_cells)
        assert grid.origin_xy == mos.origin_xy and grid.resolution_m == mos.resolution_m
        assert np.array_equal(np.load(paths["elevation"]), mos.elevation, equal_nan=True)
        assert np.array_equal(np.load(paths["labels"]), mos.labels)
    cells = map_tiles.mapped_cells(folder, n, 0.1, "cam", max_cells=10**6)
    assert len(cells.i) == 5 * 30 + 5 * 12 and set(np.unique(cells.elevation)) == {1.0, 2.0}


def test_health_counts_the_wheel_speeds_that_arrive_while_a_window_is_fitted(city_drive, tmp_path):
    config, config_path = private_config(tmp_path, mapper=SMALL_WINDOWS)
    worker = MappingWorker(config, str(config_path), str(tmp_path / "data"))
    wheels = [r for r in read_log([city_drive]) if r.topic == WHEEL_SPEEDS]
    for n, r in enumerate(wheels):
        r.message.host_mono_ns = r.log_time_ns
        worker.reader.take(r.topic, r.message)
        if n == len(wheels) // 2:
            worker.update_distance()  # the odometry takes the first half; the car drives on while a window is fitted
    half = worker.state.distance_m
    reported = json.loads(worker.health_message().detail)
    assert worker.state.distance_m == half > 10  # the second half is not taken yet
    worker.update_distance()
    assert worker.state.distance_m > 1.5 * half
    assert reported["distance_m"] == pytest.approx(worker.state.distance_m, abs=0.01)
    assert reported["lag_m"] == pytest.approx(worker.state.distance_m, abs=0.01)  # nothing mapped yet


# ---- the Lidar pose refinement asked for on a drive without Lidar ---------------------------------------------
def test_windows_without_the_asked_lidar_pose_refinement_are_counted_on_status_and_survive_a_restart(
        city_drive, tmp_path, caplog):
    refine = {"pose_refinement": {"enabled": True, "lidar_horizontal": True, "steps": 5, "blur_px": [2.0]}}
    worker = worker_fed(tmp_path / "run", city_drive, mapper=refine, leave_out=(LIDAR_PACKETS, LIDAR_IMU))
    with caplog.at_level(logging.WARNING, logger="mapping.live.worker_loop"):
        assert worker.step(end_of_drive=True) and worker.step(end_of_drive=True)  # windows 0 and 1, journalled
    entries = read_journal(tmp_path / "run" / "data" / "map").windows
    assert [e.status for e in entries] == ["done", "done"]
    assert all(e.metrics["pose_refinement_lidar_unavailable"].startswith("no Lidar ground") for e in entries)
    warnings = [r.getMessage() for r in caplog.records if "lidar_horizontal asked for" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].startswith("window 0: ")  # once; the count says the rest
    assert json.loads(worker.health_message().detail)["windows_without_lidar_refinement"] == 2
    config, config_path = private_config(tmp_path / "run", mapper=SMALL_WINDOWS | refine)
    restarted = MappingWorker(config, str(config_path), str(tmp_path / "run" / "data"))  # reads its journal
    assert json.loads(restarted.health_message().detail)["windows_without_lidar_refinement"] == 2


# ---- a drive without masks -----------------------------------------------------------------------------
def test_the_worker_maps_a_drive_without_masks_and_its_final_map_has_no_semantics(city_drive_without_masks, tmp_path,
                                                                                   caplog):
    worker = worker_fed(tmp_path / "run", city_drive_without_masks)
    with caplog.at_level(logging.WARNING, logger="mapping.live.worker_loop"):
        entries = [worker.run_window(0), worker.run_window(1)]
    warnings = [r.getMessage() for r in caplog.records if "no semantic mask" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].startswith("window 0: ")  # once, not per window
    assert f"{entries[0].frames} of {entries[0].frames} camera frames have no semantic mask" in warnings[0]
    for entry in entries:
        assert entry.status == "done" and entry.keyframes > 0 and entry.frames_without_mask == entry.frames > 0
        assert entry.metrics["miou_pct"] is None and entry.metrics["semantics"].startswith("unavailable: ")
        assert entry.metrics["keyframes_without_semantics"] == entry.keyframes
        assert 10 < entry.metrics["maskless_hidden_pct"] < 90  # the cars in view, left out by the Lidar's test
    previews = worker.previews
    assert (previews / "rgb.png").stat().st_size > 0 and (previews / "elevation.png").stat().st_size > 0
    assert not (previews / "semantics.png").exists()
    tile = map_tiles.load_tile(worker.tiles_dir / entries[0].tiles[0], worker.tile_cells, worker.cam_names)
    assert np.isfinite(tile["elevation"]).sum() > 100 and (tile["labels"] == 255).all()
    final = write_final_map(tmp_path / "final", worker.tile_store, FinalMapMetadata(
        windows=[e.to_json() for e in entries], config={}, distance_m=worker.state.distance_m,
        origin_lat_lon_alt=None))
    meta = FinalMapMetadata.read(final)
    assert meta.semantics.startswith("unavailable: ") and meta.semantics_no_label is None
    assert not list(final.glob("bev_semantics*"))
    for name in ("bev_elevation.npy", "bev_elevation.png", "bev_rgb_front_wide.png", "mesh.ply"):
        assert (final / name).stat().st_size > 0


def test_a_final_map_has_semantics_when_some_windows_had_them():
    done = lambda semantics: {"status": "done", "metrics": {"semantics": semantics}}  # noqa: E731
    assert map_semantics([done("available"), {"status": "failed"}]) == "available"
    assert map_semantics([{"status": "done", "metrics": {}}]) == "available"  # journalled before the field
    assert map_semantics([done("unavailable: x"), done("available")]).startswith("partial: 1 of 2 windows")
    assert map_semantics([done("partial: x")]).startswith("partial: 0 of 1")
    assert map_semantics([done("unavailable: x"), done("unavailable: y")]).startswith("unavailable: ")


def test_a_windows_lidar_ground_comes_with_its_firing_times_on_the_windows_clock(city_drive, tmp_path):
    """What the pose refinement's Lidar registration re-places the ground with (`reconstruct`'s
    lidar_ground_times), as offline: without them the live fit skipped the registration that `roadlog
    reconstruct` makes (city3, pose refinement on: mIoU 60.4 % live, 80.1 % offline; with them 80.7 %)."""
    from mapping.inputs.drive_inputs import start_loading_drive
    from mapping.live.window_inputs import gather_window_inputs

    worker = worker_fed(tmp_path / "run", city_drive)
    k = 2  # a window that starts after the drive's first second: its clock is not the fusion's
    inputs = gather_window_inputs(worker, k)
    assert inputs.ground_times is not None and len(inputs.ground_times) == len(inputs.ground) > 1000
    offline = start_loading_drive([str(city_drive)], worker.config, worker.config_path).result()
    shift = (inputs.t_lo_ns - int(offline.trajectory.times_ns[0])) / 1e9
    assert shift > 0.5
    from scipy.spatial import cKDTree

    distance, nearest = cKDTree(offline.lidar_ground_points).query(inputs.ground)
    same = distance < 0.001  # the same firing, placed the same way by both trajectories
    assert same.mean() > 0.5  # (the rest: the static filter over the window, not the drive, keeps others)
    off_by = np.abs(inputs.ground_times[same] + shift - offline.lidar_ground_times[nearest[same]])
    assert np.quantile(off_by, 0.95) < 1e-4  # (a few points of other scans land within 1 mm of one)
    assert -1.0 < inputs.ground_times.min() and inputs.ground_times.max() < inputs.path.duration_s + 1.0
