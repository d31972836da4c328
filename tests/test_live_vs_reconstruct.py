"""The live map of a drive (daemon replay with the mapping worker) against `roadlog reconstruct` on the
log the daemon recorded: within 0.5 dB PSNR (views both trained on), 0.5 cm elevation error (Lidar ground points
and the simulator's truth) and 5 points of bird's-eye mIoU, both maps in the live map's frame. Runs
bench/live_vs_reconstruct.py on a 3 s city drive."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_live_map_matches_the_offline_reconstruction_of_the_recorded_log():
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "live_vs_reconstruct.py"), "--quick"],
                         cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    figures = json.loads(run.stdout.strip().splitlines()[-1])
    assert figures["windows"] >= 1
    assert figures["live"]["truth_cells"] > 10_000  # both maps cover the drive
    assert abs(figures["psnr_train_db_gap"]) <= 0.5
    assert abs(figures["elev_error_cm_gap"]) <= 0.5
    assert abs(figures["elev_mae_gt_cm_gap"]) <= 0.5
    assert abs(figures["miou_pct_gap"]) <= 5.0
    assert figures["within_tolerance"]
