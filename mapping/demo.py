"""`roadlog demo`: simulate a city drive, run the daemon on it in replay mode with recording and mapping on,
then print what happened (messages logged per sensor, losses, map metrics, time taken) and where the
map images and mesh are.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from daemon.commands.log_info import summarise
from daemon.log_format.reader import read_metadata

REPO = Path(__file__).resolve().parents[1]
SIM_CONFIG = REPO / "configs" / "sim.yaml"


def recorder_losses(segments: list[Path]) -> Counter:
    lost: Counter = Counter()
    for seg in segments:
        meta = read_metadata(seg).get("roadlog.counts", {})
        lost.update(json.loads(meta.get("lost_per_topic", "{}")))
    return lost


def sensor_of(topic: str) -> str:
    return topic.split("/")[0] if "/" in topic else topic


def map_truth_metrics(map_dir: Path, gt_path: Path) -> dict:
    """Elevation error and semantic mIoU of the final map's rasters against the simulator's truth grids."""
    from daemon.spine.local_frame import LocalFrame
    from daemon.spine.semantic_classes import NUM_MAP_CLASSES
    from mapping.live.final_map import METADATA_NAME, FinalMapMetadata
    from mapping.outputs.map_metrics import confusion, miou_pct

    if not (map_dir / METADATA_NAME).exists() or not (map_dir / "bev_elevation.npy").exists():
        return {}
    meta = FinalMapMetadata.read(map_dir)
    elevation = np.load(map_dir / "bev_elevation.npy")
    labels = np.load(map_dir / "bev_semantics.npy")
    gt = np.load(gt_path)
    h, w = elevation.shape
    ii, jj = np.mgrid[0:h, 0:w]
    res_map, (x0, y0) = meta.resolution_m, meta.origin_xy
    enu = np.stack([x0 + jj.ravel() * res_map, y0 + ii.ravel() * res_map, np.nan_to_num(elevation.ravel())], 1)
    if meta.origin_lat_lon_alt:  # the map's ENU frame is the worker's: move into the truth's frame
        enu = LocalFrame(*gt["enu_origin_lat_lon_alt"]).geodetic_to_enu(
            *LocalFrame(*meta.origin_lat_lon_alt).enu_to_geodetic(enu))
    res, (ox, oy) = float(gt["grid_resolution_m"]), gt["grid_origin_xy"]
    gi = np.floor((enu[:, 1] - oy) / res).astype(int)  # the truth's origin is a cell corner
    gj = np.floor((enu[:, 0] - ox) / res).astype(int)
    inside = (gi >= 0) & (gi < gt["elevation"].shape[0]) & (gj >= 0) & (gj < gt["elevation"].shape[1])
    out = {}
    z = np.where(np.isfinite(elevation.ravel()), enu[:, 2], np.nan)
    ok = inside & np.isfinite(z)
    true_z = gt["elevation"][gi[ok], gj[ok]]
    fin = np.isfinite(true_z)
    if fin.any():
        out["elev_mae_gt_cm"] = float(100 * np.mean(np.abs(z[ok][fin] - true_z[fin])))
    lab = labels.ravel()
    ok = inside & (lab < NUM_MAP_CLASSES)
    true_l = gt["semantic"][gi[ok], gj[ok]]
    valid = true_l < NUM_MAP_CLASSES
    if valid.any():
        out["miou_pct_bev"] = miou_pct(confusion(lab[ok][valid], true_l[valid], np.ones(valid.sum(), bool)))
    windows = [wi.get("metrics", {}) for wi in meta.windows]
    for key in ("psnr_train_db", "elev_error_cm"):  # a live window holds no views out: PSNR on its training views
        values = [m[key] for m in windows if m.get(key) is not None]
        if values:
            out[f"{key}_windows_mean"] = float(np.mean(values))
    out["windows"] = len(windows)
    return out


def _roadlog(*args: str, **options) -> int:
    """`roadlog ARGS` as a step of the demo: its exit status (a failed step has said why on stderr)."""
    return subprocess.run([sys.executable, "-m", "daemon.commands.cli", *args], **options).returncode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="city")
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated drive length")
    parser.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    args = parser.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    drive = out / f"{args.scenario}.mcap"
    gt = out / f"{args.scenario}.gt.npz"
    data = out / "data"
    if data.exists():  # the demo's own folder: an earlier run's segments would be counted with this run's
        print(f"replacing the previous demo's logs and map in {data}", flush=True)
        shutil.rmtree(data)
    timings = {}

    t0 = time.monotonic()
    print(f"[1/3] simulating a {args.seconds:.0f} s {args.scenario} drive -> {drive}", flush=True)
    failed = _roadlog("simulate", "--scenario", args.scenario, "--seconds", f"{args.seconds:g}", "--out", str(drive),
                      stdout=subprocess.DEVNULL)
    if failed:  # it said why (a bad --scenario or --seconds: one error line, exit 2)
        return failed
    timings["simulate_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    print(f"[2/3] running the daemon in replay mode (recording + mapping) -> {data}", flush=True)
    failed = _roadlog("replay", str(drive), "--config", str(SIM_CONFIG), "--rate", "max", "--output-dir", str(data))
    if failed:
        return failed
    timings["daemon_s"] = time.monotonic() - t0

    print("[3/3] checking the recorded log and the map", flush=True)
    sent = summarise([drive])["messages_per_topic"]
    segments = sorted(data.glob("*.mcap"))
    recorded = summarise(segments)
    logged = Counter(recorded["messages_per_topic"])
    incomplete = [f["path"] for f in recorded["files"] if not f["complete"]]
    lost = recorder_losses(segments)
    replayed = {t for t in sent if not t.startswith(("health/", "time_anchor"))}
    rows = []
    for sensor in sorted({sensor_of(t) for t in replayed}):
        topics = [t for t in replayed if sensor_of(t) == sensor]
        s, g = sum(sent[t] for t in topics), sum(logged[t] for t in topics)
        rows.append((sensor, s, g, sum(lost[t] for t in topics)))
    map_dir = data / "map" / "final"
    metrics = map_truth_metrics(map_dir, gt)

    print()
    print(f"{'sensor':<12}{'sent':>10}{'logged':>10}{'lost':>8}")
    for sensor, s, g, lo in rows:
        print(f"{sensor:<12}{s:>10}{g:>10}{lo:>8}")
    all_logged = all(g == s for _, s, g, _ in rows)
    print(f"\nevery message logged: {'yes' if all_logged else 'NO'}; segments: {len(segments)}, "
          f"incomplete: {len(incomplete)}")
    print("map metrics: " + ", ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}"
                                      for k, v in metrics.items()))
    print(f"time: simulate {timings['simulate_s']:.0f} s, daemon (replay + record + map) {timings['daemon_s']:.0f} s")
    print("\nfiles:")
    for pattern in ("*.png", "*.tif", "*.ply", "*.glb", "*.npy", "*.json"):
        for f in sorted(map_dir.glob(pattern)):
            print(f"  {f}")
    print(f"  logs: {data}")
    return 0 if all_logged else 1


if __name__ == "__main__":
    sys.exit(main())
