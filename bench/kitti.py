"""Real drives bench: the two KITTI drives in ../shared/data imported (`roadlog import`) and mapped (`roadlog
reconstruct`, maskless: KITTI has no masks), with the import's time against the drive's length.

Runs: kitti_raw_0005 with the OXTS INS poses and with pose fusion of its GNSS + IMU, each with and without its
Velodyne ground; kitti_odometry_01 (ground-truth poses, camera only). Prints one line per run and, last, one JSON
object with every run's figures (`--quick`: 0005 with INS poses and 01 only). A camera-only map of a drive with a
Velodyne also gets `elev_vs_velodyne_cm`: its elevation raster against the drive's own Velodyne ground points
(the reconstruction's Lidar ground filter), per band of horizontal distance from the car's path
(velodyne_gap). `--pose-refinement on|off` passes that to every reconstruction (default: the config's); `both`
maps every run twice, `.../refined` with it on; `all` three times, also `.../photometric` (on without the Lidar
ground registration: the Lidar runs differ); `lidar` maps every run three times: off, `.../refined` (on) and
`.../lidar` (`--pose-refinement lidar`: every axis from the Lidar ground; camera only it is the photometric fit).
`--lidar` adds 0005's Lidar run to `--quick`. `--camera-check` maps every camera-only run again with
`--camera-check apply` (`.../camera-check`: each camera's yaw and pitch checked against the poses, and a camera
found off turned; its `camera_check` figures come with it).

    .venv/bin/python bench/kitti.py [--quick] [--lidar] [--pose-refinement on|off|both|all|lidar] [--camera-check]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
ROADLOG = str(ROOT / ".venv" / "bin" / "roadlog")
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(ROOT))

from mapping.inputs.drive_inputs import start_loading_drive  # noqa: E402
from mapping.offline.reconstruct_command import config_from_logs  # noqa: E402

KEYS = ("psnr_db", "psnr_train_db", "psnr_pixels", "psnr_by_distance_db", "saturation_rendered_pct",
        "saturation_observed_pct", "saturation_ratio", "edge_sawtooth_cm", "smear_pct", "elev_error_cm",
        "maskless_hidden_pct", "semantics", "wall_s", "rtf", "vertices", "pose_refinement",
        "pose_refinement_wall_s", "lidar_registration", "lidar_registration_wall_s",
        "lidar_horizontal_registration", "lidar_pre_pass_wall_s", "camera_check")
BANDS_M = ((0.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, 15.0))  # distance from the car's path (m)


def imported(fmt: str, folder: Path, out: Path, *extra: str) -> dict:
    started = time.perf_counter()
    done = subprocess.run([ROADLOG, "import", fmt, str(folder), "--out", str(out), *extra], check=True,
                          capture_output=True, text=True)
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    return {"import_wall_s": time.perf_counter() - started, "import_s": summary["wall_s"],
            "drive_s": summary["drive_s"]}


def mapped(log: Path, out: Path, *extra: str) -> dict:
    subprocess.run([ROADLOG, "reconstruct", str(log), "--out", str(out), *extra], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    metrics = json.loads((out / "metrics.json").read_text())
    return {k: metrics.get(k) for k in KEYS}


def velodyne_gap(log: Path, out: Path) -> dict:
    """The map's elevation raster (`out`/bev_elevation.npy, read at the cell holding each point) against the
    log's Velodyne ground points, per band of horizontal distance from the car's path (the nearest trajectory
    point): points, median and mean |map - Velodyne| (cm) and the median signed gap (cm), over the points the map
    covers."""
    config, config_path = config_from_logs([str(log)])
    loading = start_loading_drive([str(log)], config, config_path, standing=False)
    ground, track = loading.lidar_ground_points.result(), loading.path
    bev = json.loads((out / "bev.json").read_text())
    z = np.load(out / "bev_elevation.npy")
    step, (bx, by) = bev["resolution_m"], bev["origin_xy"]
    i, j = np.rint((ground[:, 1] - by) / step).astype(int), np.rint((ground[:, 0] - bx) / step).astype(int)
    inside = (i >= 0) & (i < z.shape[0]) & (j >= 0) & (j < z.shape[1])
    mapped = np.full(len(ground), np.nan)
    mapped[inside] = z[i[inside], j[inside]]
    gap = mapped - ground[:, 2]
    away = cKDTree(track.positions[:, :2]).query(ground[:, :2])[0]
    bands = {}
    for lo, hi in BANDS_M:
        g = gap[(away >= lo) & (away < hi) & np.isfinite(gap)]
        bands[f"{lo:g}-{hi:g} m"] = ({"points": len(g), "median_abs_cm": round(100 * float(np.median(np.abs(g))), 2),
                                      "mean_abs_cm": round(100 * float(np.mean(np.abs(g))), 2),
                                      "median_cm": round(100 * float(np.median(g)), 2)} if len(g) else None)
    return bands


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="0005 with its INS poses and 01, camera only")
    parser.add_argument("--pose-refinement", choices=("on", "off", "both", "all", "lidar"),
                        help="reconstruct with --pose-refinement on or off (default: the config's), both, or all "
                             "(off, photometric, on)")
    parser.add_argument("--lidar", action="store_true", help="--quick: also 0005 with its Lidar ground")
    parser.add_argument("--camera-check", action="store_true",
                        help="also map each camera-only run with --camera-check apply")
    args = parser.parse_args()
    refinements = {"on": [("", "on")], "off": [("", "off")], "both": [("", "off"), ("/refined", "on")],
                   "all": [("", "off"), ("/photometric", "photometric"), ("/refined", "on")],
                   "lidar": [("", "off"), ("/refined", "on"), ("/lidar", "lidar")],
                   None: [("", None)]}[args.pose_refinement]
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        plans = [("kitti_raw_0005-ins", "kitti-raw", DATA / "kitti_raw_0005", ("--poses", "oxts")),
                 ("kitti_odometry_01", "kitti-odometry", DATA / "kitti_odometry_01", ())]
        if not args.quick:
            plans.insert(1, ("kitti_raw_0005-fusion", "kitti-raw", DATA / "kitti_raw_0005", ("--poses", "fusion")))
        for name, fmt, folder, extra in plans:
            log = tmp / f"{name}.mcap"
            timing = imported(fmt, folder, log, *extra)
            variants = [("camera-only", ("--no-lidar",))]
            if args.camera_check:
                variants.append(("camera-only/camera-check", ("--no-lidar", "--camera-check", "apply")))
            if fmt == "kitti-raw" and (args.lidar or not args.quick):
                variants.append(("lidar", ()))
            for (variant, flags), (suffix, refinement) in ((v, r) for v in variants for r in refinements):
                refine = ("--pose-refinement", refinement) if refinement else ()
                out = tmp / f"{name}-{variant.replace('/', '-')}{suffix.replace('/', '-')}"
                figures = timing | mapped(log, out, *flags, *refine)
                if fmt == "kitti-raw" and variant.startswith("camera-only"):
                    figures["elev_vs_velodyne_cm"] = velodyne_gap(log, out)
                runs[f"{name}/{variant}{suffix}"] = figures
                print(f"{name}/{variant}{suffix}", json.dumps(figures), flush=True)
    print(json.dumps({"runs": runs}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
