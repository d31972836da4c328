"""Maskless bench: what a drive without masks maps like, with and without the Lidar occlusion test, against the
same drive with its masks.

Per simulated drive (the sim's heavy-traffic city: parked cars on both sides, oncoming traffic, a lead car) the
inputs are loaded once; three fast-fit reconstructions then differ only in their training keyframes:
- `masked`: with their masks (the reference: the masks keep cars out of the colours);
- `maskless`: without masks, every pixel in view used;
- `occlusion`: without masks, the views' pixels hidden by what the Lidar saw standing (the default).
The held-out keyframes keep their masks in all three, so `psnr_db` is the held-out PSNR over the masks'
road-surface pixels every time. `road_colour_err` is the mean |colour target - the masked fit's| (8-bit units,
mean over RGB) over the (vertex, camera) pairs on a true road-surface cell both observed: the target is the mean
colour of a vertex's accepted reads from that camera, what the colour fit is fitted to (the fitted colours of
two fits of the same targets already differ by ~7 at a vertex: the encoder's sampling); `road_colour_err_gt25_pct`
the share of those pairs off by more than 25 (a car smeared in). `hidden_by_class_pct`:
of the training views' colour reads of each class (read from the sim's masks: the true labels with a
segmenter's errors), the share the occlusion test left out; `hidden_pct` of all reads.

    .venv/bin/python bench/maskless.py [--quick] [--seconds 15] [--seeds 21 22 23]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.spine.config import load_config  # noqa: E402
from daemon.spine.semantic_classes import NUM_MAP_CLASSES, ROAD_SURFACE_CLASSES, SemanticClass  # noqa: E402
from mapping.fits import fast_fit  # noqa: E402
from mapping.fits.lidar_occlusion import OcclusionTest  # noqa: E402
from mapping.fits.reconstruction import reconstruct, select_keyframes  # noqa: E402
from mapping.fits.vertex_observations import project_points  # noqa: E402
from mapping.inputs.drive_inputs import load_drive  # noqa: E402
from mapping.method.road_map import WindowIndex  # noqa: E402
from mapping.offline.reconstruct_command import DriveTruth  # noqa: E402
from sim.drive_log import simulate_drive  # noqa: E402

CACHE = Path("/tmp/maplab")
CONFIG = ROOT / "configs" / "sim.yaml"
HOLDOUT_EVERY = 10


def _drive(seconds: float, seed: int) -> Path:
    path = CACHE / f"city{seconds:g}-seed{seed}.mcap"
    if not path.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        simulate_drive("city", seconds, path, load_config(CONFIG), seed=seed)
    return path


def _split(drive, spacing_m: float) -> tuple[list, list]:
    """The keyframes reconstruct will hold out and train on (its own rule), in its order."""
    selected = select_keyframes(drive.keyframes, drive.path, spacing_m)
    held = [i % HOLDOUT_EVERY == HOLDOUT_EVERY // 2 for i in range(len(selected))]
    return selected, held


def _road_vertices(road_map, truth: DriveTruth) -> np.ndarray:
    """Which mesh vertices lie on a true road-surface cell."""
    gt = truth.elevation
    j = np.rint((road_map.mesh.xy[:, 0] - gt.origin_xy[0]) / gt.resolution_m).astype(np.int64)
    i = np.rint((road_map.mesh.xy[:, 1] - gt.origin_xy[1]) / gt.resolution_m).astype(np.int64)
    inside = (i >= 0) & (i < gt.semantic.shape[0]) & (j >= 0) & (j < gt.semantic.shape[1])
    road = np.zeros(len(j), bool)
    road[inside] = np.isin(gt.semantic[i[inside], j[inside]], ROAD_SURFACE_CLASSES)
    return road


def _target_error(obs, reference, road: np.ndarray) -> tuple[float, float]:
    """Mean |colour target - the reference's| (8-bit) over the road (vertex, camera) pairs both observed, and
    the share (%) of them off by more than 25."""
    both = (obs.colour_count > 0) & (reference.colour_count > 0) & road[:, None]
    v, c = np.nonzero(both)
    err = np.abs(obs.colour_mean(v)[np.arange(len(v)), c] - reference.colour_mean(v)[np.arange(len(v)), c])
    err = err.mean(1) * 255
    return float(err.mean()), float(100 * (err > 25).mean())


def _hidden_by_class(road_map, train: list, drive, occlusion: OcclusionTest, config) -> dict:
    """Per true class (the masks' labels), the training views' colour reads and those the test hid."""
    mesh, windows, fast = road_map.mesh, WindowIndex.of(road_map.mesh), config.mapper.fast_fit
    reads, hidden = np.zeros(256, np.int64), np.zeros(256, np.int64)
    for kf in train:
        s = float(drive.path.horizontal_distance_at(kf.timestamp))
        a, b = np.searchsorted(windows.vertex_s, [s - fast.behind_m, s + fast.ahead_m])
        ids = windows.vertex_order[a:b]
        points = np.concatenate([mesh.xy[ids], road_map.z_now[ids, None].astype(np.float64)], 1)
        camera = drive.cameras[kf.camera]
        uv, ok = project_points(points, camera, kf.T_world_camera)
        h = occlusion.hidden(kf, camera, uv[ok], points[ok])
        if h is None:
            continue
        w = kf.semantics.shape[1]
        label = kf.semantics.reshape(-1)[np.rint(uv[ok, 1]).astype(np.int64) * w + np.rint(uv[ok, 0]).astype(np.int64)]
        reads += np.bincount(label, minlength=256)
        hidden += np.bincount(label[h], minlength=256)
    names = {int(c): c.name.lower() for c in SemanticClass}
    return {names.get(c, "unlabelled"): round(100.0 * hidden[c] / reads[c], 2) for c in np.flatnonzero(reads)
            if c < NUM_MAP_CLASSES or c == SemanticClass.OBSTACLE}


def bench_drive(seconds: float, seed: int) -> dict:
    config = load_config(CONFIG)
    log = _drive(seconds, seed)
    truth = DriveTruth.load(log.with_name(log.name.removesuffix(".mcap") + ".gt.npz"))
    drive = load_drive([log], config, CONFIG, origin=truth.origin, standing=True)
    selected, held = _split(drive, config.mapper.inputs.keyframe_spacing_m)
    maskless = [k if h else dataclasses.replace(k, semantics=None) for k, h in zip(selected, held, strict=True)]
    train = [k for k, h in zip(selected, held, strict=True) if not h]  # with their masks: the classes of reads
    train_maskless = [k for k, h in zip(maskless, held, strict=True) if not h]
    runs, maps = {}, {}
    for name, keyframes, standing in (("masked", selected, None), ("maskless", maskless, None),
                                      ("occlusion", maskless, drive.lidar_standing)):
        started = time.perf_counter()
        r = reconstruct(keyframes, drive.cameras, drive.path, drive.lidar_ground_points, config.mapper,
                        config.vehicle.reference_height_m, gt=truth.elevation, holdout_every=HOLDOUT_EVERY,
                        progress=False, lidar_standing=standing)
        m = r.metrics
        runs[name] = {"psnr_db": m["psnr_db"], "elev_error_cm": m["elev_error_cm"],
                      "vertices_observed": m["vertices_observed"], "observe_wall_s": m["observe_wall_s"],
                      "reconstruct_wall_s": time.perf_counter() - started, "hidden_pct": m.get("maskless_hidden_pct")}
        maps[name] = r.road_map
    road = _road_vertices(maps["masked"], truth)
    occlusion = OcclusionTest.of(drive.lidar_standing, config.mapper.maskless)
    targets = {name: fast_fit.observe(maps["masked"], kfs, drive.cameras, drive.path, config.mapper, False, {}, test)
               for name, kfs, test in (("masked", train, None), ("maskless", train_maskless, None),
                                       ("occlusion", train_maskless, occlusion))}
    for name in ("maskless", "occlusion"):
        runs[name]["road_colour_err"], runs[name]["road_colour_err_gt25_pct"] = _target_error(
            targets[name], targets["masked"], road)
    runs["occlusion"]["hidden_by_class_pct"] = _hidden_by_class(maps["occlusion"], train, drive, occlusion, config)
    return {"seconds": seconds, "seed": seed, "drive_s": drive.drive_s, "keyframes_train": len(train),
            "keyframes_holdout": len(selected) - len(train), **runs}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one 5 s drive")
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--seeds", type=int, nargs="+", default=[21, 22, 23])
    args = parser.parse_args()
    seconds, seeds = (5.0, args.seeds[:1]) if args.quick else (args.seconds, args.seeds)
    results = []
    for seed in seeds:
        results.append(bench_drive(seconds, seed))
        print(json.dumps(results[-1]), flush=True)

    def over_seeds(run: str, key: str, worst) -> dict:
        values = [r[run][key] for r in results]
        return {"median": float(np.median(values)), "worst": float(worst(values))}

    summary = {"machine": platform.node(), "cpus": len(__import__("os").sched_getaffinity(0)), "seeds": seeds}
    for run in ("masked", "maskless", "occlusion"):
        summary[f"psnr_db_{run}"] = over_seeds(run, "psnr_db", min)
    for run in ("maskless", "occlusion"):
        summary[f"road_colour_err_{run}"] = over_seeds(run, "road_colour_err", max)
        summary[f"road_colour_err_gt25_pct_{run}"] = over_seeds(run, "road_colour_err_gt25_pct", max)
    summary["hidden_pct"] = over_seeds("occlusion", "hidden_pct", max)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
