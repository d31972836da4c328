"""Real drives bench: the two KITTI drives in ../shared/data imported (`roadlog import`) and mapped (`roadlog
reconstruct`, maskless: KITTI has no masks), with the import's time against the drive's length.

Runs: kitti_raw_0005 with the OXTS INS poses and with pose fusion of its GNSS + IMU, each with and without its
Velodyne ground; kitti_odometry_01 (ground-truth poses, camera only). Prints one line per run and, last, one JSON
object with every run's figures (`--quick`: 0005 with INS poses and 01 only). `--pose-refinement on|off` passes
that to every reconstruction (default: the config's); `both` maps every run twice, `.../refined` with it on.

    .venv/bin/python bench/kitti.py [--quick] [--pose-refinement on|off|both]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ROADLOG = str(ROOT / ".venv" / "bin" / "roadlog")
DATA = ROOT.parent / "shared" / "data"
KEYS = ("psnr_db", "psnr_train_db", "psnr_pixels", "psnr_by_distance_db", "saturation_rendered_pct",
        "saturation_observed_pct", "saturation_ratio", "edge_sawtooth_cm", "smear_pct", "elev_error_cm",
        "maskless_hidden_pct", "semantics", "wall_s", "rtf", "vertices", "pose_refinement",
        "pose_refinement_wall_s")


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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="0005 with its INS poses and 01, camera only")
    parser.add_argument("--pose-refinement", choices=("on", "off", "both"),
                        help="reconstruct with --pose-refinement on or off (default: the config's), or both")
    args = parser.parse_args()
    refinements = {"on": [("", "on")], "off": [("", "off")], "both": [("", "off"), ("/refined", "on")],
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
            if fmt == "kitti-raw" and not args.quick:
                variants.append(("lidar", ()))
            for (variant, flags), (suffix, refinement) in ((v, r) for v in variants for r in refinements):
                refine = ("--pose-refinement", refinement) if refinement else ()
                figures = timing | mapped(log, tmp / f"{name}-{variant}{suffix.replace('/', '-')}", *flags, *refine)
                runs[f"{name}/{variant}{suffix}"] = figures
                print(f"{name}/{variant}{suffix}", json.dumps(figures), flush=True)
    print(json.dumps({"runs": runs}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
