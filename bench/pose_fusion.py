"""Pose-fusion cost and accuracy: a simulated 10-minute drive (2 with --quick) and the comma2k19 segment.

Run by hand: `python bench/pose_fusion.py [--quick]`; the last line is one JSON object.
"""

import argparse
import importlib.util
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the package `mapping`, not bench/mapping.py beside this script

from mapping.localization.pose_fusion import fuse_trajectory  # noqa: E402

TESTS = ROOT / "tests" / "mapping" / "test_pose_fusion.py"


def load_simulator():
    """The drive simulator lives with the tests that define what a correct fusion is."""
    spec = importlib.util.spec_from_file_location("test_pose_fusion", TESTS)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def timed_fusion(sim, drive, repeats: int):
    wall, cpu = [], []
    for _ in range(repeats):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        result = fuse_trajectory(drive.gnss, drive.imu, drive.wheels, sim.MOUNTING)
        wall.append(time.perf_counter() - start_wall)
        cpu.append(time.process_time() - start_cpu)
    return result, statistics.median(wall), statistics.median(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="a 2-minute drive, one repeat (under a minute)")
    args = parser.parse_args()
    sim = load_simulator()
    minutes = 2.0 if args.quick else 10.0
    repeats = 1 if args.quick else 3
    figures: dict[str, object] = {"drive_minutes": minutes, "repeats": repeats}
    for name, sigma_h, sigma_v in (("rtk", 0.015, 0.025), ("metre", 1.5, 2.0)):
        drive = sim.simulate_drive(minutes * 60.0, sigma_h, sigma_v, seed=11)
        result, wall, cpu = timed_fusion(sim, drive, repeats)
        errors = sim.pose_errors(result.trajectory, drive.truth)
        figures[name] = {"fuse_wall_s": round(wall, 3), "fuse_cpu_s": round(cpu, 3),
                         "cpu_s_per_data_minute": round(cpu / minutes, 3),
                         **{key: round(value, 4) for key, value in errors.items()}}
        print(name, figures[name], flush=True)
    gnss, imu, wheels, truth = sim.load_comma_drive()
    start = time.process_time()
    result = fuse_trajectory(gnss, imu, wheels, sim.COMMA_MOUNTING)
    errors = sim.pose_errors(sim.device_trajectory(result), truth)
    mounting = Rotation.from_matrix(result.imu_to_vehicle @ sim.FRD_TO_FLU.T).magnitude()
    figures["comma2k19"] = {"fuse_cpu_s": round(time.process_time() - start, 3),
                            "estimated_mounting_rotation_deg": round(float(np.degrees(mounting)), 2),
                            **{key: round(value, 4) for key, value in errors.items()}}
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
