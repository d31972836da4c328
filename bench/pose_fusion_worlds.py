"""Fused roll, pitch, yaw and lateral position against the truth on the roadlog simulator's worlds: random worlds
1..N and the seeded city drive (seed 3), 8 s each (--quick: worlds 1-3 and the city, 4 s).

The GNSS, IMU and CAN streams are the ones `roadlog simulate` logs (the same stream builders in sim/drive_log.py,
through the GNSS and CAN drivers' decoders, with the sensors' clocks), fused by
mapping/inputs/drive_inputs.fuse_log_trajectory as the mapper does; no camera or Lidar is rendered.
Per world: mean and worst roll, pitch and yaw error (deg) and lateral position error (cm, across the true heading),
and the lateral error's spread within 1 s (cm: its RMS after a 1 s running mean is taken out, the part that differs
between the views of one spot); over the worlds: the median and worst of the mean |error| and the worst error.
`--no-velocity` fuses the fixes without the receiver's velocities (`gnss/velocity`), as logs without them are.

    .venv/bin/python bench/pose_fusion_worlds.py [--quick] [--worlds 5] [--seconds 8] [--no-velocity]

The last line is one JSON object.
"""

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the package `mapping`, not bench/mapping.py beside this script

from daemon.spine.config import load_config, resolve_path  # noqa: E402
from daemon.spine.local_frame import LocalFrame  # noqa: E402
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU, WHEEL_SPEEDS  # noqa: E402
from mapping.inputs.drive_inputs import fuse_log_trajectory  # noqa: E402
from mapping.localization.sensor_time import fit_clocks  # noqa: E402
from sim import drive_log  # noqa: E402
from sim.sensors.sensor_clocks import HOST_MONO_AT_START_NS, drive_clocks, host_mono_ns, utc_start_ns  # noqa: E402
from sim.world.random_world import scenario_for  # noqa: E402
from sim.world.scene import build_scene  # noqa: E402


def fused_errors(name: str, seed: int, seconds: float, velocity: bool = True) -> dict[str, float]:
    config = load_config(drive_log.DEFAULT_CONFIG)
    scenario = scenario_for(name, seed, [c.name for c in config.sensors.cameras])
    scene = build_scene(scenario, config, seconds, seed, seed)
    clocks = drive_clocks(scene.config, scenario, np.random.default_rng([seed, 4]))
    frame = LocalFrame(scenario.origin.latitude_deg, scenario.origin.longitude_deg, scenario.origin.altitude_m)
    items = drive_log._gnss_imu_messages(scene, clocks, frame, np.random.default_rng([seed, 5]))
    dbc = resolve_path(drive_log.DEFAULT_CONFIG, scene.config.sensors.can.dbc_file)
    items += drive_log._can_messages(scene, clocks, dbc, np.random.default_rng([seed, 6]))
    utc0 = utc_start_ns(scenario)
    anchors = [(host_mono_ns(k), utc0 + k * 1_000_000_000) for k in range(int(seconds) + 2)]
    by_topic: dict[str, list] = {GNSS_FIX: [], GNSS_VELOCITY: [], IMU: [], WHEEL_SPEEDS: []}
    for _, topic, message in items:
        if topic in by_topic:
            by_topic[topic].append(message)
    fit = fit_clocks(by_topic, anchors)
    trajectory = fuse_log_trajectory(by_topic[GNSS_FIX], by_topic[IMU], by_topic[WHEEL_SPEEDS], scene.config, frame,
                                     fit, by_topic[GNSS_VELOCITY] if velocity else [])
    position, quat = trajectory.interpolate(trajectory.times_ns)
    true_s = (trajectory.times_ns - HOST_MONO_AT_START_NS) * 1e-9
    true_rotation, true_position = scene.ego.pose(true_s)
    left = true_rotation[:, :, 1]  # the vehicle's y axis (left) in ENU
    lateral_cm = 100.0 * np.einsum("ij,ij->i", position - true_position, left)
    window = max(1, int(round(1.0 / float(np.median(np.diff(true_s))))))
    lateral_fast_cm = lateral_cm - np.convolve(lateral_cm, np.ones(window) / window, mode="same")
    lateral_fast_cm = lateral_fast_cm[window:-window] if len(lateral_cm) > 3 * window else lateral_fast_cm
    error = (Rotation.from_quat(quat).as_euler("ZYX", degrees=True)
             - Rotation.from_matrix(scene.ego.sample("rotation", true_s)).as_euler("ZYX", degrees=True))
    error = (error + 180.0) % 360.0 - 180.0
    return {"roll_mean_deg": round(float(error[:, 2].mean()), 3),
            "roll_worst_deg": round(float(np.abs(error[:, 2]).max()), 3),
            "pitch_mean_deg": round(float(error[:, 1].mean()), 3),
            "pitch_worst_deg": round(float(np.abs(error[:, 1]).max()), 3),
            "yaw_mean_deg": round(float(error[:, 0].mean()), 3),
            "yaw_worst_deg": round(float(np.abs(error[:, 0]).max()), 3),
            "lateral_mean_cm": round(float(lateral_cm.mean()), 2),
            "lateral_worst_cm": round(float(np.abs(lateral_cm).max()), 2),
            "lateral_1s_rms_cm": round(float(np.sqrt(np.mean(lateral_fast_cm ** 2))), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="worlds 1-3 and the city, 4 s (under a minute)")
    parser.add_argument("--worlds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--no-velocity", action="store_true", help="fuse without the receiver's velocities")
    args = parser.parse_args()
    worlds, seconds = (3, 4.0) if args.quick else (args.worlds, args.seconds)
    figures: dict[str, object] = {"seconds": seconds, "velocity": not args.no_velocity}
    runs = [("random", seed) for seed in range(1, worlds + 1)] + [("city", 3)]
    for name, seed in runs:
        figures[f"{name}_{seed}"] = fused_errors(name, seed, seconds, not args.no_velocity)
        print(f"{name}_{seed}", figures[f"{name}_{seed}"], flush=True)
    per_world = [figures[f"{name}_{seed}"] for name, seed in runs]
    for angle, unit in (("roll", "deg"), ("pitch", "deg"), ("yaw", "deg"), ("lateral", "cm")):
        means = [abs(w[f"{angle}_mean_{unit}"]) for w in per_world]
        figures[f"{angle}_abs_mean_{unit}_median"] = round(statistics.median(means), 3)
        figures[f"{angle}_abs_mean_{unit}_worst"] = round(max(means), 3)
        figures[f"{angle}_worst_{unit}"] = round(max(w[f"{angle}_worst_{unit}"] for w in per_world), 3)
    figures["lateral_1s_rms_cm_worst"] = max(w["lateral_1s_rms_cm"] for w in per_world)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
