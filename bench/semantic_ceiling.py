"""How high can the bird's-eye mIoU of a map with per-vertex semantic logits go? The ceiling of the
representation, with perfect labels: every vertex of the road mesh gets the true class (from the simulated
drive's truth grid) and the map is scored exactly as `roadlog reconstruct --gt` scores it (logits
interpolated over the triangle under every other 5 cm truth cell, argmax, mIoU over the five classes).

Two ways of giving a vertex its label: `point` (the class at the vertex, what one observation at the
vertex's projection reads) and `footprint` (the classes at the vertex and half-way to its six neighbours,
weighted as its hat function: what a per-pixel loss spreads over a triangle's vertices). Mesh sides 0.1 m
(the paper's) and 0.05 m. The drive comes from bench/mapping.py's cache (simulated once).

    .venv/bin/python bench/semantic_ceiling.py [--quick] [--scenario city] [--seconds 10]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from daemon.spine.semantic_classes import NUM_MAP_CLASSES  # noqa: E402
from mapping.localization.trajectory import HorizontalTrack  # noqa: E402
from mapping.method.road_mesh import build_road_mesh, locate  # noqa: E402
from mapping.offline.reconstruct_command import DriveTruth  # noqa: E402
from mapping.outputs.map_metrics import confusion, truth_cells  # noqa: E402

_spec = importlib.util.spec_from_file_location("mapping_bench", Path(__file__).with_name("mapping.py"))
mapping_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(mapping_bench)

HALF_WIDTH_M = 15.0


def true_class_at(truth: DriveTruth, xy: np.ndarray) -> np.ndarray:
    g = truth.elevation
    h, w = truth.semantic.shape
    j = np.rint((xy[:, 0] - g.origin_xy[0]) / g.resolution_m).astype(np.int64)
    i = np.rint((xy[:, 1] - g.origin_xy[1]) / g.resolution_m).astype(np.int64)
    inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    out = np.full(len(xy), 255, np.uint8)
    out[inside] = truth.semantic[i[inside], j[inside]]
    return out


def vertex_labels(truth: DriveTruth, xy: np.ndarray, side_m: float, footprint: bool) -> np.ndarray:
    """(N, classes) label weights of vertices at `xy`."""
    samples = [(0.0, 0.0, 1.0)]
    if footprint:
        samples += [(0.5 * side_m * np.cos(a), 0.5 * side_m * np.sin(a), 0.5) for a in np.arange(6) * np.pi / 3]
    out = np.zeros((len(xy), NUM_MAP_CLASSES), np.float32)
    for dx, dy, weight in samples:
        label = true_class_at(truth, xy + [dx, dy])
        known = label < NUM_MAP_CLASSES
        out[np.flatnonzero(known), label[known]] += weight
    return out


def ceiling(truth: DriveTruth, trajectory: HorizontalTrack, side_m: float, footprint: bool) -> dict:
    mesh = build_road_mesh(trajectory, HALF_WIDTH_M, side_m, 0.0)
    labels = vertex_labels(truth, mesh.xy, side_m, footprint)
    rows, cols, xy = truth_cells(truth.elevation)  # the cells the bird's-eye mIoU is taken on
    ids, weights, ok = locate(mesh, xy)
    pred = (labels[ids[ok]] * weights[ok][..., None]).sum(1).argmax(1)
    true = truth.semantic[rows[ok], cols[ok]]
    valid = true < NUM_MAP_CLASSES
    conf = confusion(pred[valid], true[valid], np.ones(int(valid.sum()), bool))
    inter = np.diag(conf).astype(np.float64)
    iou = inter / np.maximum(conf.sum(0) + conf.sum(1) - inter, 1)
    return {"miou_pct": round(100.0 * float(iou.mean()), 1), "iou": [round(float(v), 3) for v in iou]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a 3 s drive")
    parser.add_argument("--scenario", default="city")
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    log = mapping_bench.drive(args.scenario, 3.0 if args.quick else args.seconds)
    truth = DriveTruth.load(log.with_suffix(".gt.npz"))
    gt = np.load(log.with_suffix(".gt.npz"))
    trajectory = HorizontalTrack(gt["trajectory_host_mono_ns"] * 1e-9, gt["trajectory_position_enu"].astype(np.float64))
    result: dict[str, object] = {"scenario": args.scenario, "log": str(log),
                                 "classes": ["road", "lane_marking", "curb", "manhole", "background"]}
    for side in (0.1, 0.05):
        for footprint in (False, True):
            key = f"side_{side:g}_{'footprint' if footprint else 'point'}"
            result[key] = ceiling(truth, trajectory, side, footprint)
            print(key, result[key], flush=True)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
