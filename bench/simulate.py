"""Benchmark `roadlog simulate`: wall-clock and CPU time of a city drive with three cameras at 10 Hz and
the OS-128 at 1024x10 (the issue's target: a 30 s drive in under 2 minutes on 2 cores).

Run: .venv/bin/python bench/simulate.py [--quick] [--seconds S] [--scenario NAME] [--workers N]
The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from daemon.spine.config import load_config  # noqa: E402
from sim.drive_log import DEFAULT_CONFIG, simulate_drive  # noqa: E402


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a 5 s drive (under a minute)")
    parser.add_argument("--seconds", type=float, default=None)
    parser.add_argument("--scenario", default="city")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    seconds = args.seconds or (5.0 if args.quick else 30.0)
    config = load_config(DEFAULT_CONFIG)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / f"{args.scenario}.mcap"
        cpu0, wall0 = _cpu_s(), time.perf_counter()
        summary = simulate_drive(args.scenario, seconds, out, config, config_dir=DEFAULT_CONFIG.parent,
                                 workers=args.workers)
        wall, cpu = time.perf_counter() - wall0, _cpu_s() - cpu0
        gt_bytes = summary.ground_truth.stat().st_size
    result = {
        "bench": "simulate",
        "scenario": args.scenario,
        "drive_s": seconds,
        "workers": args.workers,
        "cpus_available": len(os.sched_getaffinity(0)),
        "load_average_1min": os.getloadavg()[0],
        "camera_frames": summary.camera_frames,
        "lidar_scans": summary.lidar_scans,
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "wall_s_per_drive_s": round(wall / seconds, 2),
        "setup_s": round(summary.setup_s, 1),
        "render_and_write_s": round(summary.render_s, 1),
        "ground_truth_s": round(summary.ground_truth_s, 1),
        "mcap_mb": round(summary.bytes_written / 1e6, 1),
        "gt_npz_mb": round(gt_bytes / 1e6, 1),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
