"""Random-worlds bench (issue 17 item 4): map quality as the median and worst over random worlds, never one seed.

Simulates N random worlds (`roadlog simulate --scenario random --seed S`, seeds first..first+N-1) and, for
comparison, the fixed `city` scenario (seed 12), then runs `roadlog reconstruct --gt` on each with Lidar and
with `--no-lidar` (the config recorded in each log), and reports per run and as median / worst: held-out PSNR,
bird's-eye mIoU, lane-marking and curb IoU, Elev-error and the elevation MAE against the true grid, and that
MAE on the road surface only (truth classes road, marking, curb, manhole; read from the 10 cm elevation raster
at each true cell, so not the metric's own interpolation). The targets are checked on the random worlds'
medians: with Lidar lane marking >= 85 %, curb >= 80 %, mIoU >= 92 %; camera-only elevation MAE vs truth
<= 5 cm. The last line is one JSON object.

    .venv/bin/python bench/worlds.py [--quick] [--worlds 5] [--seconds 8] [--first-seed 1] [--no-city] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ROADLOG = str(ROOT / ".venv" / "bin" / "roadlog")
CITY_SEED = 12
# figure -> (metrics.json key, iou_pct class or None, better: "high" or "low")
FIGURES = {
    "psnr_db": ("psnr_db", None, "high"),
    "miou_pct": ("miou_pct", None, "high"),
    "lane_marking_iou_pct": ("iou_pct", "lane_marking", "high"),
    "curb_iou_pct": ("iou_pct", "curb", "high"),
    "elev_error_cm": ("elev_error_cm", None, "low"),
    "elev_mae_gt_cm": ("elev_mae_gt_cm", None, "low"),
    "elev_mae_road_cm": (None, None, "low"),  # from the rasters (road_surface_mae_cm)
}
TARGETS = {  # (run, figure, bound, "min" or "max") on the random worlds' median
    "lidar lane marking IoU >= 85 %": ("lidar", "lane_marking_iou_pct", 85.0, "min"),
    "lidar curb IoU >= 80 %": ("lidar", "curb_iou_pct", 80.0, "min"),
    "lidar mIoU >= 92 %": ("lidar", "miou_pct", 92.0, "min"),
    "camera-only elevation MAE vs truth <= 5 cm": ("no_lidar", "elev_mae_gt_cm", 5.0, "max"),
}
RUNS = {"lidar": (), "no_lidar": ("--no-lidar",)}


def simulate(scenario: str, seed: int, seconds: float, out: Path) -> dict:
    done = subprocess.run([ROADLOG, "simulate", "--scenario", scenario, "--seed", str(seed), "--seconds",
                           str(seconds), "--out", str(out)], check=True, cwd=ROOT, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def reconstruct(log: Path, out: Path, *extra: str) -> dict:
    subprocess.run([ROADLOG, "reconstruct", str(log), "--out", str(out), "--gt", str(log.with_suffix(".gt.npz")),
                    *extra], check=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    m = json.loads((out / "metrics.json").read_text())
    figures = {}
    for name, (key, cls, _) in FIGURES.items():
        value = m.get(key)
        figures[name] = (value or {}).get(cls) if cls else value
    figures["elev_mae_road_cm"] = road_surface_mae_cm(out, log.with_suffix(".gt.npz"))
    figures["wall_s"] = m.get("wall_s")
    return figures


def road_surface_mae_cm(out: Path, gt_path: Path) -> float | None:
    """Mean |z - z_true| (cm) over the true road-surface cells (5 cm) the map's elevation raster covers, the
    raster read at the cell holding each true cell's centre."""
    bev = json.loads((out / "bev.json").read_text())
    z = np.load(out / "bev_elevation.npy")
    gt = np.load(gt_path)
    res, (x0, y0) = float(gt["grid_resolution_m"]), gt["grid_origin_xy"]
    rows, cols = np.nonzero(np.isin(gt["semantic"], (0, 1, 2, 3)) & np.isfinite(gt["elevation"]))
    x, y = x0 + (cols + 0.5) * res, y0 + (rows + 0.5) * res
    step, (bx, by) = bev["resolution_m"], bev["origin_xy"]  # raster cell (i, j) centred at (bx + j step, by + i step)
    i, j = np.rint((y - by) / step).astype(int), np.rint((x - bx) / step).astype(int)
    inside = (i >= 0) & (i < z.shape[0]) & (j >= 0) & (j < z.shape[1])
    mapped = np.full(len(x), np.nan)
    mapped[inside] = z[i[inside], j[inside]]
    known = np.isfinite(mapped)
    if not known.any():
        return None
    return float(100 * np.mean(np.abs(mapped[known] - gt["elevation"][rows[known], cols[known]])))


def summarise(values: list[float | None], better: str) -> dict:
    present = [v for v in values if v is not None]
    if not present:
        return {"median": None, "worst": None, "missing": len(values)}
    worst = min(present) if better == "high" else max(present)
    return {"median": statistics.median(present), "worst": worst, "missing": len(values) - len(present)}


def fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def table(worlds: list[dict], city: dict | None, stats: dict) -> str:
    head = ("| world | run | PSNR dB | mIoU % | lane marking IoU % | curb IoU % | Elev-error cm | MAE vs truth cm "
            "| MAE road surface cm |\n|---|---|---|---|---|---|---|---|---|")
    rows = [head]
    for w in worlds + ([city] if city else []):
        for run in RUNS:
            f = w[run]
            rows.append(f"| {w['label']} | {run.replace('_', '-')} | " + " | ".join(fmt(f[k]) for k in FIGURES) + " |")
    for run in RUNS:
        s = stats[run]
        rows.append(f"| **median** | {run.replace('_', '-')} | " + " | ".join(fmt(s[k]["median"]) for k in FIGURES)
                    + " |")
        rows.append(f"| **worst** | {run.replace('_', '-')} | " + " | ".join(fmt(s[k]["worst"]) for k in FIGURES)
                    + " |")
    return "\n".join(rows)


def run_world(scenario: str, seed: int, seconds: float, folder: Path) -> dict:
    started = time.perf_counter()
    log = folder / f"{scenario}_{seed}.mcap"
    summary = simulate(scenario, seed, seconds, log)
    world = summary.get("world") or {}
    result = {"scenario": scenario, "seed": seed, "label": f"{scenario} {seed}",
              "description": world.get("description", scenario)}
    for run, extra in RUNS.items():
        result[run] = reconstruct(log, folder / f"{scenario}_{seed}_{run}", *extra)
    result["wall_s"] = time.perf_counter() - started
    print(json.dumps(result), flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one world of 4 s, no city (under a minute)")
    parser.add_argument("--worlds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--no-city", action="store_true", help="leave out the fixed city scenario")
    parser.add_argument("--out", type=Path, help="keep the drives and maps here (default: a temporary folder)")
    args = parser.parse_args()
    count, seconds = (1, 4.0) if args.quick else (args.worlds, args.seconds)
    with_city = not (args.quick or args.no_city)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        worlds = [run_world("random", args.first_seed + i, seconds, folder) for i in range(count)]
        city = run_world("city", CITY_SEED, seconds, folder) if with_city else None
    stats = {run: {name: summarise([w[run][name] for w in worlds], better)
                   for name, (_, _, better) in FIGURES.items()} for run in RUNS}
    targets = {}
    for label, (run, figure, bound, kind) in TARGETS.items():
        median = stats[run][figure]["median"]
        met = median is not None and (median >= bound if kind == "min" else median <= bound)
        targets[label] = {"median": median, "worst": stats[run][figure]["worst"], "met": met}
    print(table(worlds, city, stats))
    for w in worlds:
        print(f"- {w['description']}")
    for label, t in targets.items():
        print(f"{label}: median {fmt(t['median'])}, worst {fmt(t['worst'])}: {'met' if t['met'] else 'not met'}")
    print(json.dumps({"bench": "worlds", "worlds": count, "seconds": seconds, "first_seed": args.first_seed,
                      "cpus_available": len(os.sched_getaffinity(0)), "load_average_1min": os.getloadavg()[0],
                      "wall_s": round(time.perf_counter() - started, 1), "median_worst": stats, "targets": targets,
                      "runs": worlds, "city": city}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
