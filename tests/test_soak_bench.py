"""bench/soak.py --quick as a real process: the whole daemon on the looping drive, stopped cleanly, and its accounts
close: for every topic, what was sent is what was logged plus what the recorder counted lost plus what was counted
lost before the driver (the Lidar's numbering, a full GNSS pseudo-terminal): on a loaded machine messages may be
lost, never silently."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from daemon.log_format.reader import summary_message_counts

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.timeout(900)  # the drive simulated, the daemon started on a loaded machine, 40 s driven, stopped
def test_the_quick_soak_stops_cleanly_and_accounts_for_every_message(city_drive, tmp_path):
    run = subprocess.run([sys.executable, str(REPO / "bench" / "soak.py"), "--quick", "--drive", str(city_drive),
                          "--work", str(tmp_path / "soak")], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["stop_exit_code"] == 0 and result["orphans"] == [] and result["segments_open_after_stop"] == []
    assert result["passes_done"] == result["passes_planned"] == 8  # 40 s of a 5 s drive
    assert result["segments_unreadable"] == [] and result["segments"] >= 4  # 10 s segments
    for topic, row in result["topics"].items():
        assert row["sent"] > 0 and row["unaccounted"] == 0, (topic, row)
    per_pass = summary_message_counts(city_drive)
    assert result["topics"]["lidar/packets"]["sent"] == 8 * per_pass["lidar/packets"]  # every pass's, none twice
    assert result["topics"]["wheel_speeds"]["sent"] == 8 * per_pass["wheel_speeds"]
    names = {"supervisor", "recorder", "lidar", "gnss", "can", "status", "mapper",
             "camera_front_wide", "camera_front_left", "camera_front_right"}
    assert names <= set(result["rss"]) and all(r["max_mb"] > 0 for r in result["rss"].values())
