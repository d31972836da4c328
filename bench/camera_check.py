"""Camera check bench (mapping/localization/camera_orientation.py): how well each camera's yaw and pitch are read
from its keyframes, over random simulated worlds and on the real KITTI drives.

Per random world (`roadlog simulate --scenario random --seed S`): the check on the recorded config (the mounts the
images were rendered with: every reading is an error, and a camera found off is a false alarm), then on a config
with every camera turned by a random yaw and pitch of up to --turn-deg (seeded; the reading should be the turn back:
its error is reading + turn, and a turn above warn_deg that is not found is a miss). With --maps, each world is also
mapped (`roadlog reconstruct --gt`, with Lidar) three ways: the true config, the turned one, the turned one with
`--camera-check apply`. With --kitti the three KITTI logs (0005 with INS poses and fused, 01) are imported and
checked. Medians and worst cases; the last line is one JSON object.

    .venv/bin/python bench/camera_check.py [--quick] [--worlds 5] [--seconds 8] [--first-seed 1] [--turn-deg 2]
                                           [--maps] [--kitti]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from daemon.spine.config import CarConfig, config_to_yaml  # noqa: E402
from mapping.inputs.drive_inputs import load_drive  # noqa: E402
from mapping.localization.camera_orientation import check_orientations, significant  # noqa: E402
from mapping.offline.reconstruct_command import config_from_logs  # noqa: E402

ROADLOG = str(ROOT / ".venv" / "bin" / "roadlog")
DATA = ROOT.parent / "shared" / "data"
KITTI = {"0005-ins": ("kitti-raw", "kitti_raw_0005", ("--poses", "oxts")),
         "0005-fused": ("kitti-raw", "kitti_raw_0005", ("--poses", "fusion")),
         "01": ("kitti-odometry", "kitti_odometry_01", ())}


def turned(config: CarConfig, turns: dict[str, tuple[float, float]]) -> CarConfig:
    """The config with each camera's mount turned by (pitch, yaw) degrees about the vehicle's axes."""
    cameras = []
    for cam in config.sensors.cameras:
        pitch, yaw = turns[cam.name]
        rotation = (Rotation.from_euler("xyz", (0.0, pitch, yaw), degrees=True)
                    * Rotation.from_euler("xyz", cam.extrinsics.rotation_rpy_deg, degrees=True))
        rpy = tuple(float(v) for v in rotation.as_euler("xyz", degrees=True))
        extrinsics = cam.extrinsics.model_copy(update={"rotation_rpy_deg": rpy})
        cameras.append(cam.model_copy(update={"extrinsics": extrinsics}))
    return config.model_copy(update={"sensors": config.sensors.model_copy(update={"cameras": cameras})})


def readings(log: Path, config: CarConfig, config_path: Path) -> dict[str, dict | None]:
    drive = load_drive([str(log)], config, config_path, use_lidar=False)
    setting = config.mapper.camera_check
    return {name: None if check is None else {**check.summary(), "off": significant(check, setting)}
            for name, check in check_orientations(drive.keyframes, drive.cameras, setting).items()}


def mapped(log: Path, config: CarConfig, config_path: Path, out: Path, *extra: str) -> dict:
    """`roadlog reconstruct --gt` with this config, written beside `config_path` (where the recorded config's Lidar
    metadata file is)."""
    written = config_path.with_name(f"{out.name}.yaml")
    written.write_text(config_to_yaml(config))
    subprocess.run([ROADLOG, "reconstruct", str(log), "--out", str(out), "--config", str(written),
                    "--gt", str(log.with_suffix(".gt.npz")), *extra], check=True, cwd=ROOT,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    m = json.loads((out / "metrics.json").read_text())
    return {"psnr_db": m["psnr_db"], "miou_pct": m["miou_pct"],
            "lane_marking_iou_pct": (m.get("iou_pct") or {}).get("lane_marking")}


def world(seed: int, seconds: float, turn_deg: float, folder: Path, maps: bool) -> dict:
    log = folder / f"world{seed}.mcap"
    subprocess.run([ROADLOG, "simulate", "--scenario", "random", "--seed", str(seed), "--seconds", str(seconds),
                    "--out", str(log)], check=True, cwd=ROOT, capture_output=True)
    config, config_path = config_from_logs([str(log)])
    rng = np.random.default_rng(1000 + seed)
    turns = {c.name: tuple(float(v) for v in rng.uniform(-turn_deg, turn_deg, 2)) for c in config.sensors.cameras}
    bad = turned(config, turns)
    result = {"seed": seed, "turns_pitch_yaw_deg": turns, "true": readings(log, config, config_path),
              "turned": readings(log, bad, config_path)}
    if maps:
        result["maps"] = {"true": mapped(log, config, config_path, folder / f"world{seed}-true"),
                          "turned": mapped(log, bad, config_path, folder / f"world{seed}-turned"),
                          "turned_apply": mapped(log, bad, config_path, folder / f"world{seed}-apply",
                                                 "--camera-check", "apply")}
    return result


def errors(worlds: list[dict], warn_deg: float) -> dict:
    """Per camera kind (forward: front_wide; sides: the others), the readings' absolute errors (deg) on true and on
    turned mounts, all of them and those with a verdict (read from at least as many pairs as were refused:
    camera_orientation.significant), the false alarms (a true mount found off), the turns found and missed (above
    warn_deg), the readings without a verdict and the cameras with no reading."""
    out = {}
    for kind, wanted in (("forward", lambda n: n == "front_wide"), ("sides", lambda n: n != "front_wide")):
        err = {"true": [], "turned": [], "true_verdict": [], "turned_verdict": []}
        alarms = found = missed = no_verdict = unread = 0
        for w in worlds:
            for run in ("true", "turned"):
                for name, r in w[run].items():
                    if not wanted(name):
                        continue
                    if r is None:
                        unread += 1
                        continue
                    pitch, yaw = w["turns_pitch_yaw_deg"][name] if run == "turned" else (0.0, 0.0)
                    e = [abs(r["pitch_deg"] + pitch), abs(r["yaw_deg"] + yaw)]
                    err[run] += e
                    verdict = r["pairs_used"] >= r["pairs_refused"]
                    no_verdict += not verdict
                    if verdict:
                        err[f"{run}_verdict"] += e
                    if run == "true":
                        alarms += r["off"]
                    elif max(abs(pitch), abs(yaw)) > warn_deg:
                        found += r["off"]
                        missed += not r["off"]
        out[kind] = {**{f"{k}_median_deg": statistics.median(v) if v else None for k, v in err.items()},
                     **{f"{k}_worst_deg": max(v, default=None) for k, v in err.items()},
                     "false_alarms": alarms, "turns_found": found, "turns_missed": missed,
                     "readings_without_verdict": no_verdict, "unread": unread}
    return out


def kitti(folder: Path) -> dict:
    out = {}
    for name, (fmt, data, extra) in KITTI.items():
        log = folder / f"kitti-{name}.mcap"
        subprocess.run([ROADLOG, "import", fmt, str(DATA / data), "--out", str(log), *extra], check=True,
                       capture_output=True)
        config, config_path = config_from_logs([str(log)])
        out[name] = readings(log, config, config_path)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one 4 s world, no maps, no KITTI (under a minute)")
    parser.add_argument("--worlds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--turn-deg", type=float, default=2.0, help="the turned mounts' largest yaw and pitch")
    parser.add_argument("--maps", action="store_true", help="also map each world true / turned / turned + apply")
    parser.add_argument("--kitti", action="store_true", help="also check the three KITTI logs")
    args = parser.parse_args()
    if args.quick:
        args.worlds, args.seconds, args.maps, args.kitti = 1, 4.0, False, False
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        worlds = []
        for seed in range(args.first_seed, args.first_seed + args.worlds):
            worlds.append(world(seed, args.seconds, args.turn_deg, folder, args.maps))
            print(json.dumps(worlds[-1]), flush=True)
        real = kitti(folder) if args.kitti else None
        if real is not None:
            print(json.dumps({"kitti": real}), flush=True)
    warn_deg = CarConfig.model_fields["mapper"].default.camera_check.warn_deg
    summary = {"worlds": args.worlds, "seconds": args.seconds, "turn_deg": args.turn_deg, "warn_deg": warn_deg,
               "errors": errors(worlds, warn_deg), "kitti": real, "wall_s": round(time.perf_counter() - started, 1)}
    if args.maps:
        summary["maps"] = {run: {k: [w["maps"][run][k] for w in worlds] for k in worlds[0]["maps"][run]}
                           for run in ("true", "turned", "turned_apply")}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
