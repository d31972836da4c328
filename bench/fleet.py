"""Fleet bench (issue 20 items 2-3): two simulated drives of one road (`roadlog simulate --scenario city --visit 0`
and `--visit 1`: the same world, other traffic, light, noise and GNSS offset) mapped by `roadlog fleet reconstruct`
on a local Ray with 1 and with 2 workers, and the merged map measured against the world's truth beside each drive's
own map (its windows fused, unaligned: what that drive alone gives):

- coverage: the fraction of the true road surface (road, marking, curb, manhole) within 12 m of the tracks that
  the map covers (merged_coverage, best_single_coverage, per drive);
- mIoU (%) of the map's labels against the true classes where both have one; elevation MAE (cm) against the true
  surface height (ellipsoidal, through the truth's ENU origin) on the mapped road cells;
- the drives' true GNSS offsets and the alignment the merge estimated;
- speedup_2_workers: the fleet's task wall time (Ray start excluded, reported apart) with 1 worker over 2; the
  load average is printed beside it (this machine is shared: the figure is noisy).

Targets: merged coverage above either drive's; merged mIoU and elevation MAE at least the better drive's.

    .venv/bin/python bench/fleet.py [--quick] [--seconds S] [--seed N] [--visits A,B] [--drives DIR] [--out DIR]
                                    [--reuse]

--quick: 4 s drives and a coarse, short mapper (0.2 m cells, 60 m windows, a keyframe every 2 m, every 4th Lidar
scan, 40 elevation steps); the full bench's drives, mapper and figures are unchanged by it. --seed: the world's
seed (default the city's own, 11); --visits: which two visits (default 0,1; visit 0 has no GNSS offset, so as
placed it is the truth's own frame: `--visits 1,2` gives both drives another day's offset). --drives keeps the
simulated drives between runs (simulating a 4 s drive: 70 s here at a load of 5); --reuse with --out keeps
finished fleet jobs too (a rerun to try a merge costs only the merge and the scores). The last line is one JSON
object.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.log_format.reader import read_metadata  # noqa: E402
from daemon.spine.local_frame import LocalFrame  # noqa: E402
from daemon.spine.semantic_classes import NUM_MAP_CLASSES, ROAD_SURFACE_CLASSES  # noqa: E402
from mapping.fleet.drive_merge import MAX_SHIFT_M, DriveLayer, drive_layers, estimate_shift, fuse  # noqa: E402
from mapping.fleet.geodetic_grid import utm_to_enu_xy  # noqa: E402
from mapping.fleet.tile_store import TileStore  # noqa: E402
from mapping.method.road_map import NO_LABEL  # noqa: E402
from mapping.outputs.map_metrics import confusion, miou_pct  # noqa: E402

ROADLOG = str(ROOT / ".venv" / "bin" / "roadlog")
NEAR_TRACK_M = 12.0
QUICK_MAPPER = """mapper:
  mesh: {side_m: 0.2, corridor_half_width_m: 13.0}
  windows: {before_m: 30.0, after_m: 30.0}
  inputs: {keyframe_spacing_m: 2.0, lidar_every_n_scans: 4}
  fast_fit: {elevation_min_steps: 40, lidar_detail_passes: 2}
"""


def simulate(drives: Path, seconds: float, seed: int | None, visits: list[int]) -> list[Path]:
    """The visits' logs, each simulated (side by side, a process each) unless it is already in `drives`."""
    logs, running = [], []
    for visit in visits:
        log = drives / f"city{'' if seed is None else seed}_{seconds:g}s_v{visit}.mcap"
        if not (log.exists() and log.with_name(log.stem + ".gt.npz").exists()):
            running.append(subprocess.Popen(
                [ROADLOG, "simulate", "--scenario", "city", "--seconds", str(seconds), "--visit", str(visit),
                 "--out", str(log), *(["--seed", str(seed)] if seed is not None else [])], stdout=subprocess.DEVNULL))
        logs.append(log)
    for proc in running:
        if proc.wait() != 0:
            raise subprocess.CalledProcessError(proc.returncode, proc.args)
    return logs


def finished_job(logs: list[Path], out: Path, mapper: Path | None) -> dict | None:
    """The summary of a job in `out` that mapped exactly these logs with this mapper and failed nothing (None:
    there is none): its maps are reused, its timings are the ones measured when it ran."""
    try:
        summary = json.loads((out / "fleet.json").read_text())
        bench = json.loads((out / "bench_job.json").read_text())
    except (OSError, ValueError):
        return None
    same = bench == {"logs": [str(p) for p in logs], "mapper": mapper.read_text() if mapper else None}
    ok = summary.get("windows") and summary["windows_done"] == summary["windows"] and not summary["failures"]
    return summary if same and ok else None


def run_fleet(logs: list[Path], out: Path, workers: int, mapper: Path | None, reuse: bool = False) -> dict:
    if reuse and (done := finished_job(logs, out, mapper)) is not None:
        return done | {"reused": True}
    shutil.rmtree(out, ignore_errors=True)
    cmd = [ROADLOG, "fleet", "reconstruct", *map(str, logs), "--out", str(out), "--workers", str(workers)]
    cmd += ["--mapper", str(mapper)] if mapper else []
    started = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"fleet reconstruct failed ({done.returncode}): {done.stderr[-3000:]}")
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    (out / "bench_job.json").write_text(json.dumps({"logs": [str(p) for p in logs],
                                                    "mapper": mapper.read_text() if mapper else None}))
    return summary | {"command_wall_s": time.perf_counter() - started, "reused": False}


class Truth:
    """The world's truth on a zone mosaic's cells."""

    def __init__(self, gt_path: Path, mosaic, tracks_enu: list[np.ndarray], offset_en_m: tuple[float, float] = (0, 0)):
        """`offset_en_m`: the truth sampled that far (UTM east, north) from each cell's centre."""
        self.args = (gt_path, mosaic, tracks_enu)
        gt = np.load(gt_path)
        frame = LocalFrame(*(float(v) for v in gt["enu_origin_lat_lon_alt"]))
        res_t = float(gt["grid_resolution_m"])
        h, w = mosaic.shape
        jj, ii = np.meshgrid(np.arange(w), np.arange(h))
        e = mosaic.origin_xy[0] + jj.ravel() * mosaic.resolution_m + offset_en_m[0]
        n = mosaic.origin_xy[1] + ii.ravel() * mosaic.resolution_m + offset_en_m[1]
        xy = utm_to_enu_xy(frame, e, n, mosaic.zone, mosaic.south, frame.alt_m)
        ti = np.floor((xy[:, 1] - gt["grid_origin_xy"][1]) / res_t).astype(np.int64)
        tj = np.floor((xy[:, 0] - gt["grid_origin_xy"][0]) / res_t).astype(np.int64)
        rows, cols = gt["elevation"].shape
        inside = (ti >= 0) & (ti < rows) & (tj >= 0) & (tj < cols)
        ti, tj = np.where(inside, ti, 0), np.where(inside, tj, 0)
        z = np.where(inside, gt["elevation"][ti, tj], np.nan)
        self.cls = np.where(inside, gt["semantic"][ti, tj], 255).reshape(h, w)
        ok = np.isfinite(z)
        height = np.full(len(z), np.nan)
        height[ok] = frame.enu_to_geodetic(np.column_stack([xy[ok], z[ok]]))[2]
        self.height = height.reshape(h, w)
        self.resolution_m = mosaic.resolution_m
        from scipy.spatial import cKDTree

        track = cKDTree(np.concatenate(tracks_enu)[:, :2])
        near = track.query(xy, distance_upper_bound=NEAR_TRACK_M)[0]
        self.road = (np.isin(self.cls, [int(c) for c in ROAD_SURFACE_CLASSES])
                     & np.isfinite(near).reshape(h, w) & np.isfinite(self.height))


def one_hot_layer(name: str, height: np.ndarray, labels: np.ndarray) -> DriveLayer:
    prob = np.zeros((*labels.shape, NUM_MAP_CLASSES), np.float32)
    ok = labels < NUM_MAP_CLASSES
    prob[ok, labels[ok]] = 1.0
    return DriveLayer(name, height.astype(np.float32), np.isfinite(height).astype(np.float32), prob, {})


def scores(truth: Truth, height: np.ndarray, labels: np.ndarray) -> dict:
    """As placed, and registered: the truth sampled where the map's markings, curbs and manholes overlay it best
    (drive_merge.estimate_shift, below a cell: the truth is resampled, the map is not) and the median height
    difference to the truth there taken out. Registered figures measure the map itself; what they take out is
    where the drives' positioning (GNSS) put it, reported as shift_to_truth_m and height_offset_cm."""
    placed = _scores(truth, height, labels)
    found = estimate_shift(one_hot_layer("truth", truth.height, truth.cls), one_hot_layer("map", height, labels),
                           int(np.ceil(MAX_SHIFT_M / truth.resolution_m)), truth.resolution_m)
    di, dj = found.shift or (0.0, 0.0)
    # the map's cell x matches the truth's at x + (di, dj) cells
    moved = Truth(*truth.args, offset_en_m=(dj * truth.resolution_m, di * truth.resolution_m))
    on_road = np.isfinite(height) & moved.road
    dz = float(np.median(height[on_road] - moved.height[on_road]))
    registered = _scores(moved, height - np.float32(dz), labels)
    return placed | {f"{k}_registered": v for k, v in registered.items() if k != "cells_mapped"} | {
        "shift_to_truth_m": [-dj * truth.resolution_m, -di * truth.resolution_m], "height_offset_cm": dz * 100}


def _scores(truth: Truth, height: np.ndarray, labels: np.ndarray) -> dict:
    mapped = np.isfinite(height)
    road = truth.road
    labelled = (labels != NO_LABEL) & (truth.cls < NUM_MAP_CLASSES) & mapped
    on_road = mapped & road
    return {"coverage": float((mapped & road).sum() / road.sum()),
            "miou_pct": miou_pct(confusion(labels[labelled].astype(np.int64), truth.cls[labelled].astype(np.int64),
                                           np.ones(int(labelled.sum()), bool))),
            "elev_mae_cm": float(np.mean(np.abs(height[on_road] - truth.height[on_road])) * 100),
            "cells_mapped": int(mapped.sum())}


def single(layer: DriveLayer) -> tuple[np.ndarray, np.ndarray]:
    labels = (np.where(layer.prob.sum(-1) > 0, layer.prob.argmax(-1), NO_LABEL).astype(np.uint8)
              if layer.prob is not None else np.full(layer.height.shape, NO_LABEL, np.uint8))
    return layer.height, labels


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="6 s drives, a coarse mapper")
    parser.add_argument("--seconds", type=float, help="drive length (default 4 quick, 12 otherwise)")
    parser.add_argument("--seed", type=int, help="the world's seed (default: the city scenario's)")
    parser.add_argument("--visits", default="0,1", help="the two visits of the world mapped (default 0,1)")
    parser.add_argument("--drives", type=Path, help="folder keeping the simulated drives between runs")
    parser.add_argument("--out", type=Path, help="folder of the fleet jobs (default: a temporary one)")
    parser.add_argument("--reuse", action="store_true",
                        help="reuse the jobs in --out that mapped the same drives with the same mapper (only the "
                             "merge and the scores run again; the timings are those measured when they ran)")
    args = parser.parse_args()
    started = time.perf_counter()
    seconds = args.seconds or (4.0 if args.quick else 12.0)
    visits = [int(v) for v in args.visits.split(",")]
    if len(visits) != 2 or len(set(visits)) != 2 or min(visits) < 0:
        parser.error(f"--visits {args.visits}: two different visits >= 0, e.g. 0,1")
    work = args.out
    if work is None:  # a scratch folder, gone when the bench exits
        work = Path(tempfile.mkdtemp(prefix="bench-fleet-"))
        atexit.register(shutil.rmtree, work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    drives = args.drives or work / "drives"
    drives.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    logs = simulate(drives, seconds, args.seed, visits)
    simulate_s = time.perf_counter() - t0
    mapper = None
    if args.quick:
        mapper = work / "mapper.yaml"
        mapper.write_text(QUICK_MAPPER)
    one = run_fleet(logs, work / "job_1_worker", 1, mapper, args.reuse)
    load_1 = os.getloadavg()
    two = run_fleet(logs, work / "job_2_workers", 2, mapper, args.reuse)
    load_2 = os.getloadavg()
    (mosaic,) = drive_layers(TileStore(work / "job_2_workers"))
    merged = fuse(mosaic)
    gts = [log.with_name(log.stem + ".gt.npz") for log in logs]
    tracks = [np.load(g)["trajectory_position_enu"] for g in gts]
    truth = Truth(gts[0], mosaic, tracks)
    names = {json.loads((p / "drive.json").read_text())["logs"][0]: p.name
             for p in (work / "job_2_workers" / "journal").iterdir()}
    per_drive = {}
    for log in logs:
        drive = names[str(log)]
        meta = read_metadata(log)["roadlog"]
        per_drive[log.stem] = scores(truth, *single(mosaic.layers[drive])) | {
            "drive": drive, "gnss_offset_enu_m": json.loads(meta.get("gnss_offset_enu_m", "[0, 0, 0]"))}
    merged_scores = scores(truth, merged.height, merged.labels)
    best = max(per_drive.values(), key=lambda s: s["coverage"])
    figures = {
        "merged_coverage": merged_scores["coverage"],
        "best_single_coverage": best["coverage"],
        "merged_miou_pct": merged_scores["miou_pct"],
        "merged_registered": {k: merged_scores[k] for k in ("miou_pct_registered", "elev_mae_cm_registered",
                                                            "shift_to_truth_m", "height_offset_cm")},
        "single_registered": {k: {x: v[x] for x in ("miou_pct_registered", "elev_mae_cm_registered",
                                                    "shift_to_truth_m", "height_offset_cm")}
                              for k, v in per_drive.items()},
        "single_miou_pct": {k: v["miou_pct"] for k, v in per_drive.items()},
        "merged_elev_mae_cm": merged_scores["elev_mae_cm"],
        "single_elev_mae_cm": {k: v["elev_mae_cm"] for k, v in per_drive.items()},
        "single_coverage": {k: v["coverage"] for k, v in per_drive.items()},
        "gnss_offsets_enu_m": {k: v["gnss_offset_enu_m"] for k, v in per_drive.items()},
        "alignment": [{k: a.get(k) for k in ("drive", "reference", "shift_m", "shift_std_m", "dz_m", "overlap_cells")}
                      for a in merged.alignment],
        "drive_ids": {k: v["drive"] for k, v in per_drive.items()},
        "speedup_2_workers": one["tasks_wall_s"] / two["tasks_wall_s"],
        "jobs_reused": [one["reused"], two["reused"]],
        "tasks_wall_s_1_worker": one["tasks_wall_s"], "tasks_wall_s_2_workers": two["tasks_wall_s"],
        "ray_start_s": [one["ray_start_s"], two["ray_start_s"]],
        "load_average_after_1_and_2_workers": [list(load_1), list(load_2)],
        "cpus": os.cpu_count(),
        "window_s": [s for d in json.loads((work / "job_2_workers" / "fleet.json").read_text())["drives"]
                     for s in d.get("window_s", [])],
        "drive_load_s": [d.get("load_s") for d in json.loads((work / "job_2_workers" / "fleet.json").read_text())[
            "drives"]],
        "simulate_s": simulate_s, "seconds": seconds, "quick": args.quick, "seed": args.seed, "visits": visits,
    }
    single_mious = [v for v in figures["single_miou_pct"].values() if v is not None]
    figures["targets"] = {
        "coverage_above_each_drive": figures["merged_coverage"] > max(figures["single_coverage"].values()),
        "miou_at_least_best_drive": (merged_scores["miou_pct"] or 0) >= max(single_mious, default=0),
        "elev_mae_at_most_best_drive": figures["merged_elev_mae_cm"] <= min(figures["single_elev_mae_cm"].values()),
        "registered_miou_at_least_best_drive": (merged_scores["miou_pct_registered"] or 0) >= max(
            (v["miou_pct_registered"] or 0) for v in per_drive.values()),
        "registered_elev_mae_at_most_best_drive": merged_scores["elev_mae_cm_registered"] <= min(
            v["elev_mae_cm_registered"] for v in per_drive.values()),
    }
    figures["wall_s"] = time.perf_counter() - started
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
