"""Replay determinism: the map of a log depends on the log's content only, not on when or how it was played.

Replays move the recorded host times onto this host's clock, so each replay's host times differ by an
offset, and the worker's bus reader takes topics in turns, so messages reach the spool in another order
each time. The fast test feeds the real worker the same log twice, at two host-clock offsets and in two
orders, and compares window 0; the slow one replays a drive twice through the real daemon
(`roadlog replay --rate max`) and compares the final maps.
"""

import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from mapping.live import map_tiles
from mapping.live.final_map import FinalMapMetadata
from mapping.live.odometry import Odometry
from mapping.localization.sensor_time import span_clock
from tests.daemon_fixtures import REPO, private_config
from tests.mapping.fed_worker import SMALL_WINDOWS, worker_fed

UTC_2026_NS = 1_790_000_000_000_000_000


def test_utc_clock_moves_exactly_with_the_host_clock_offset():
    stamps = UTC_2026_NS + np.arange(0, 10_000_000_000, 100_000_000) + 12_345  # GNSS epochs, 10 Hz
    anchor_mono = np.arange(0, 11_000_000_000, 1_000_000_000) + 7_000_000_000_123
    anchors = [(int(m), int(UTC_2026_NS - 7_000_000_000_000 + m + 3 * (m % 7))) for m in anchor_mono]  # jitter
    host = stamps - UTC_2026_NS + 7_000_000_000_000 + 5_000_000  # arrivals 5 ms after the epoch
    results = []
    for shift in (0, 123_456_789_012, 9_999_999_999_999):
        clock = span_clock(stamps.tolist(), (host + shift).tolist(), [(m + shift, u) for m, u in anchors])
        assert clock.kind == "utc"
        results.append(clock.to_host(stamps) - shift)
        assert np.abs(results[-1] - (host - 5_000_000)).max() <= 18  # the epochs on the host clock (anchor jitter)
    assert np.array_equal(results[0], results[1]) and np.array_equal(results[0], results[2])


def test_odometry_integrates_wheel_speeds_and_resumes_from_its_knots():
    t = 1_000_000_000 + np.arange(0, 501) * 20_000_000  # 50 Hz for 10 s
    speed = np.where(t < 6e9, 10.0, 5.0)
    odo = Odometry()
    assert all(odo.add(int(a), float(v)) for a, v in zip(t, speed, strict=True))
    assert not odo.add(int(t[-1]), 5.0)  # not after the last message: ignored
    assert odo.distance_m == pytest.approx(10.0 * 5.0 + 5.0 * 5.0, abs=0.1)
    assert odo.knots_t[-1] == t[-1] and np.all(np.diff(odo.knots_t[:-1]) >= 500_000_000)
    assert odo.time_at(50.0) == pytest.approx(6e9, abs=2e7) and odo.time_at(-1) == t[0]
    first = Odometry()
    for a, v in zip(t[:200], speed[:200], strict=True):
        first.add(int(a), float(v))
    resumed = Odometry(list(first.knots_t), list(first.knots_s), first.last_speed_mps)  # from the journal
    for a, v in zip(t[200:], speed[200:], strict=True):
        resumed.add(int(a), float(v))
    assert resumed.knots_t == odo.knots_t and resumed.knots_s == odo.knots_s


def test_a_window_is_the_same_whatever_the_host_clock_offset_and_arrival_order(city_drive, tmp_path):
    shifts = (10_000_000_000_000, 10_000_000_000_000 + 987_654_321_987)
    entries, tiles = [], []
    for n, shift in enumerate(shifts):
        worker = worker_fed(tmp_path / f"run{n}", city_drive, shift, topic_by_topic=n == 1)
        entries.append(worker.run_window(0).to_json())
        tiles.append({name: map_tiles.load_tile(worker.tiles_dir / name, worker.tile_cells, worker.cam_names)
                      for name in entries[-1]["tiles"]})
    a, b = entries
    assert a["keyframes"] == b["keyframes"] > 0 and a["lidar_ground_points"] == b["lidar_ground_points"] > 0
    assert [x - shifts[0] for x in a["host_time_ns"]] == [x - shifts[1] for x in b["host_time_ns"]]
    for key in ("psnr_train_db", "elev_error_cm", "miou_pct", "loss_last", "vertices_observed"):
        assert a["metrics"][key] == b["metrics"][key], key
    assert a["tiles"] == b["tiles"]
    for name in a["tiles"]:
        for key, value in tiles[0][name].items():
            assert np.array_equal(value, tiles[1][name][key], equal_nan=True), (name, key)


def _replay_through_the_daemon(drive: Path, folder: Path) -> Path:
    folder.mkdir()
    _, config_path = private_config(folder, mapper=SMALL_WINDOWS, status={"port": 0})
    data = folder / "data"
    done = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "replay", str(drive),
                           "--config", str(config_path),
                           "--rate", "max", "--output-dir", str(data)], cwd=REPO, capture_output=True, text=True,
                          timeout=1200)
    assert done.returncode == 0, done.stderr[-3000:]
    return data / "map"


MACHINE_STATE = ("wall_s", "rss_mb_after_window")  # the process's times and memory, not the map's figures


def _figures(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if not k.endswith(MACHINE_STATE)}


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_replaying_a_log_twice_through_the_daemon_gives_the_same_map(city_drive, tmp_path):
    maps = [_replay_through_the_daemon(city_drive, tmp_path / f"run{n}") for n in range(2)]
    metas = [asdict(FinalMapMetadata.read(m / "final")) for m in maps]
    a, b = metas
    assert len(a["windows"]) == len(b["windows"]) >= 4 and a["distance_m"] == b["distance_m"]
    for wa, wb in zip(a["windows"], b["windows"], strict=True):
        assert wa["status"] == wb["status"] == "done"
        assert wa["host_time_ns"][1] - wa["host_time_ns"][0] == wb["host_time_ns"][1] - wb["host_time_ns"][0]
        assert (wa["keyframes"], wa["lidar_packets"]) == (wb["keyframes"], wb["lidar_packets"])
        assert _figures(wa["metrics"]) == _figures(wb["metrics"])
    assert (a["origin_xy"], a["shape"]) == (b["origin_xy"], b["shape"])
    for name in ("bev_elevation.npy", "bev_semantics.npy"):
        x, y = (np.load(m / "final" / name) for m in maps)
        assert np.allclose(x, y, rtol=0, atol=1e-6, equal_nan=True), name
    tiles = sorted(p.name for p in (maps[0] / "tiles").glob("tile_*.npz"))
    assert tiles == sorted(p.name for p in (maps[1] / "tiles").glob("tile_*.npz")) and tiles
    for name in tiles:
        with np.load(maps[0] / "tiles" / name) as x, np.load(maps[1] / "tiles" / name) as y:
            for key in x.files:
                assert np.allclose(x[key], y[key], rtol=0, atol=1e-6, equal_nan=True), (name, key)
