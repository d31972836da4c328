"""The quick start's demo (`roadlog demo`): simulate, replay through the daemon with recording and mapping,
and check that every message was logged. Run twice into the same folder: the second run's table counts
its own logs only."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_demo_logs_every_message_and_maps_even_when_run_again(tmp_path):
    for _ in range(2):
        run = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "demo", "--seconds", "4",
                              "--out", str(tmp_path)],
                             cwd=ROOT, capture_output=True, text=True, timeout=900)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        rows = re.findall(r"^(\w+)\s+(\d+)\s+(\d+)\s+(\d+)$", run.stdout, re.MULTILINE)
        assert {r[0] for r in rows} >= {"camera", "lidar", "gnss", "imu", "can", "wheel_speeds", "mask"}
        assert all(sent == logged and lost == "0" for _, sent, logged, lost in rows), rows
        # one: the 4 s drive is within segment_seconds of log time (the recorder's segments follow the messages' time,
        # not how long the replay and its map took); the table counts this run's, not the first run's beside them
        assert "every message logged: yes; segments: 1, incomplete: 0" in run.stdout
        assert (tmp_path / "data" / "map" / "final" / "mesh.ply").stat().st_size > 0
