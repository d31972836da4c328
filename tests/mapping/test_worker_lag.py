"""The live mapping worker, the real process on the real bus, when it cannot keep up and when it is stopped
(mapping.live.lag_policy): its first health before torch loads, windows skipped ahead when it is too far behind the
car (journalled, counted in its health), and a SIGTERM whose remaining windows would not fit in its stop timeout:
journalled as skipped, the final map of the windows it fitted written, exit 0 within the timeout.

The mapper is made slow by `mapper.lag.min_window_wall_s` (a window takes at least 6 s, 60 m of this drive); cheap
windows (10 m, a 0.5 m mesh) keep the fits short. Whether window 0 is fitted or already skipped depends on how soon its
inputs are all in (they reach 2 s, 20 m, past its end); either way the car gets more than 25 m (`max_behind_m`) past
the next window while one is fitted, and the stop has room for one window, never for two.
"""

import json
import signal
import threading
import time

import numpy as np
import pytest

from daemon.bus import pubsub
from daemon.processes.replay import replay
from daemon.spine.topics import health_topic
from mapping.live.final_map import FinalMapMetadata
from mapping.live.window_schedule import windows_for_drive
from mapping.live.worker_journal import read_journal
from tests.daemon_fixtures import private_config, wait_for
from tests.mapping.test_mapping_worker import _start_worker

WINDOW_M = 5.0  # before and after: 10 m windows, centres every 5 m
MAPPER = {"windows": {"before_m": WINDOW_M, "after_m": WINDOW_M},
          "mesh": {"side_m": 0.5, "corridor_half_width_m": 4.0}, "inputs": {"keyframe_spacing_m": 2.0},
          "lag": {"max_behind_m": 25.0, "min_window_wall_s": 6.0, "stop_reserve_s": 50.0}}
STOP_TIMEOUT_S = 60.0  # less the reserve: 10 s after SIGTERM, room for one window (>= 6 s) but never two


# imported first by the worker's Python (sitecustomize): writes the monotonic time at which torch starts to load
TORCH_WATCH = """
import importlib.abc, sys, time

class TorchWatch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "torch":
            sys.meta_path.remove(self)
            with open({out!r}, "w") as f:
                f.write(str(time.monotonic_ns()))
        return None

sys.meta_path.insert(0, TorchWatch())
"""


def _detail(msg) -> dict:
    return json.loads(msg.detail)


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_a_worker_behind_skips_ahead_and_a_stop_leaves_what_cannot_finish_in_time(city_drive, tmp_path):
    data = tmp_path / "data"
    config, config_path = private_config(tmp_path, mapper=MAPPER, recorder={"output_dir": str(data)})
    log = tmp_path / "worker.log"
    hook = tmp_path / "hook"
    hook.mkdir()
    torch_at = tmp_path / "torch_import_ns"
    (hook / "sitecustomize.py").write_text(TORCH_WATCH.format(out=str(torch_at)))
    proc = _start_worker(config_path, log, "--stop-timeout-s", f"{STOP_TIMEOUT_S:g}", path_first=hook)
    try:
        health = pubsub.open_subscriber(config, health_topic("mapper"), start="oldest", wait_s=120)
        first = wait_for(lambda: health.read(0, copy=True), 60, "the first health")
        assert first.state == "starting" and "loading" in _detail(first)["starting"]
        up = wait_for(lambda: (m := health.latest()) is not None and m.state != "starting" and m, 300, "the worker up")
        assert first.host_mono_ns < int(torch_at.read_text()) < up.host_mono_ns  # the first health before torch
        assert _detail(up)["windows_done"] == 0
        player = threading.Thread(target=replay, args=(config, [city_drive]), kwargs={"rate": 1.0})
        player.start()
        behind = wait_for(lambda: (m := health.latest()) is not None and _detail(m)["windows_skipped"] > 0
                          and _detail(m), 600, "windows skipped", poll_s=0.5)
        player.join()
        assert behind["max_behind_m"] == 25.0
        assert health.latest().state == "degraded"  # the map has gaps: said, never silent
        stopped_at = time.monotonic()
        proc.send_signal(signal.SIGTERM)  # it is fitting the window it skipped to; the one after cannot fit
        assert proc.wait(timeout=STOP_TIMEOUT_S) == 0, log.read_text()[-3000:]
        stop_s = time.monotonic() - stopped_at
        final = _detail(health.latest())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        pubsub.unlink_all(config)
    assert stop_s < STOP_TIMEOUT_S
    journal = read_journal(data / "map")
    windows = [w.to_json() for w in journal.windows]
    distance = journal.odometry_s[-1]
    assert [w["index"] for w in windows] == list(range(windows_for_drive(distance, WINDOW_M, WINDOW_M)))
    statuses = [w["status"] for w in windows]
    reasons = [w.get("reason", "").split(":")[0] for w in windows]
    # skipped to the newest ended window; at the stop (the drive's last windows, whose inputs reach past the end of
    # the data, wait for the end of the drive) one more is fitted at most, the rest is skipped
    n_stop = reasons.count("stop")
    assert n_stop >= 1 and reasons[-n_stop:] == ["stop"] * n_stop, reasons
    assert "behind" in reasons and set(reasons[:-n_stop]) <= {"", "behind"}, reasons
    assert 1 <= statuses.count("done") <= 2, statuses
    assert {s for s, r in zip(statuses, reasons, strict=True) if r} == {"skipped"}
    for w in windows:
        if w["status"] == "skipped":  # where it was, for `roadlog reconstruct` on the log
            assert w["host_time_ns"][0] < w["host_time_ns"][1] and w["segments"] == []  # no recorder: no segment
        if w.get("reason", "").startswith("behind"):
            assert "ended" in w["reason"] and "behind the car (mapper.lag.max_behind_m 25)" in w["reason"]
    assert windows[-1]["reason"].startswith(f"stop: {n_stop} window(s) of ~")
    assert final["finished"] and final["bus_lost"] == 0 and final["windows_skipped"] == statuses.count("skipped")
    assert final["windows_done"] == statuses.count("done")
    for w in windows:  # its memory after each window (freed heap given back), for soaks to follow
        assert w["status"] != "done" or 0 < w["metrics"]["rss_mb_after_window"] <= final["peak_rss_mb"]
    assert final["stop"]["windows"] == n_stop and final["stop"]["first"] == len(windows) - n_stop
    assert abs(final["skipped_m"] - WINDOW_M * final["windows_skipped"]) <= WINDOW_M  # central stretches, 5 m each
    meta = FinalMapMetadata.read(data / "map" / "final")
    assert [w["status"] for w in meta.windows] == statuses
    elevation = np.load(data / "map" / "final" / "bev_elevation.npy")
    tiles = [np.load(data / "map" / "tiles" / name)["elevation"]
             for name in {name for w in windows if w["status"] == "done" for name in w["tiles"]}]
    assert np.isfinite(elevation).sum() == sum(np.isfinite(t).sum() for t in tiles) > 0  # what it fitted
