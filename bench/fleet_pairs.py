"""Fleet merge over several worlds (issue 20's accuracy target): for each world seed, its visits simulated and
mapped in one `roadlog fleet reconstruct` job, then every pair of visits merged (drive_merge.fuse on the pair's
layers) and scored against the world's truth beside the better of the two drives' own maps (bench/fleet.py's
scores: coverage, mIoU and elevation MAE, as placed and registered). Also the merged map scored on the better
drive's own cells only (`*_on_best_cells`): what the merge does to what that drive mapped, without the cells only
the other drive reached.

    .venv/bin/python bench/fleet_pairs.py [--quick] [--seeds 11,3,7] [--visits 0,1,2] [--seconds 6]
                                          [--drives DIR] [--out DIR] [--baseline FILE]

--quick: one world (seed 11), one pair (visits 0,1), 4 s drives: a check that the bench and a merge run, not a
figure (one pair has no median). --drives and --out default to temporary folders.

The jobs use bench/fleet.py's quick mapper and are kept in --out (a rerun with the same drives fits nothing).
--baseline: another version of mapping/fleet/drive_merge.py (e.g. `git show REV:mapping/fleet/drive_merge.py >
F.py`), merged and scored in the same run beside this one (repeatable). Prints one line per pair and, last, one
JSON object: every pair's figures and, per figure, the median and worst of merged less the better drive and how
many pairs met the target (coverage above, mIoU at least, MAE at most the better drive's).
"""

from __future__ import annotations

import argparse
import atexit
import importlib.util
import itertools
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
sys.path.insert(0, str(ROOT))

from fleet import QUICK_MAPPER, Truth, run_fleet, scores, simulate, single  # noqa: E402

from mapping.fleet import drive_merge  # noqa: E402
from mapping.fleet.tile_store import TileStore  # noqa: E402

FIGURES = {  # figure: +1 higher is better, -1 lower is better
    "coverage": 1, "miou_pct": 1, "miou_pct_registered": 1, "elev_mae_cm": -1, "elev_mae_cm_registered": -1}


def load_merge(path: Path):
    spec = importlib.util.spec_from_file_location(f"baseline_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def pair_scores(merge, store: TileStore, truth_of, pair: tuple[str, str]) -> dict:
    """The pair's merged map and both drives' own maps scored; merged on the better drive's cells too."""
    (mosaic,) = merge.drive_layers(store)
    mosaic.layers = {d: mosaic.layers[d] for d in pair}
    truth = truth_of(mosaic)
    merged = merge.fuse(mosaic)
    drives = {d: scores(truth, *single(mosaic.layers[d])) for d in pair}
    out = {"merged": scores(truth, merged.height, merged.labels), "drives": drives}
    for figure, sign in FIGURES.items():
        if figure == "coverage":
            continue
        best = max(pair, key=lambda d: sign * (drives[d][figure] if drives[d][figure] is not None else -sign * 1e9))
        cells = np.isfinite(mosaic.layers[best].height)
        height = np.where(cells, merged.height, np.nan).astype(np.float32)
        labels = np.where(cells, merged.labels, drive_merge.NO_LABEL).astype(np.uint8)
        out.setdefault("merged_on_best_cells", {})[figure] = scores(truth, height, labels)[figure]
    out["alignment"] = [{k: a.get(k) for k in ("drive", "shift_m", "dz_m", "tilt_cm_per_m")} for a in merged.alignment]
    return out


def summary(rows: list[dict], key: str) -> dict:
    """Per figure: merged (or merged on the best drive's cells) less the better drive, median and worst, and how
    many pairs met the target."""
    out = {}
    for figure, sign in FIGURES.items():
        deltas = []
        for row in rows:
            values = [d[figure] for d in row["drives"].values()]
            merged = row[key][figure] if key == "merged" else row[key].get(figure)
            if merged is None or any(v is None for v in values):
                continue
            best = max(values) if sign > 0 else min(values)
            deltas.append(merged - best)
        if not deltas:
            continue
        d = np.array(deltas)
        met = int((d > 0).sum() if figure == "coverage" and key == "merged" else (sign * d >= 0).sum())
        out[figure] = {"median": float(np.median(d)), "worst": float(d.min() if sign > 0 else d.max()),
                       "met": met, "of": len(d)}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one world, one pair of 4 s drives")
    parser.add_argument("--seeds", default="11,3,7")
    parser.add_argument("--visits", default="0,1,2")
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--drives", type=Path, help="folder keeping the simulated drives (default: temporary)")
    parser.add_argument("--out", type=Path, help="folder keeping the fleet jobs (default: temporary)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--baseline", type=Path, action="append", default=[],
                        help="another drive_merge.py, scored beside this one (named by its file's stem; repeatable)")
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.visits, args.seconds = "11", "0,1", 4.0
    if args.drives is None or args.out is None:
        scratch = Path(tempfile.mkdtemp(prefix="bench-fleet-pairs-"))  # gone when the bench exits
        atexit.register(shutil.rmtree, scratch, ignore_errors=True)
        args.drives, args.out = args.drives or scratch / "drives", args.out or scratch / "jobs"
    args.drives, args.out = args.drives.resolve(), args.out.resolve()
    started = time.perf_counter()
    visits = [int(v) for v in args.visits.split(",")]
    merges = {"this": drive_merge} | {path.stem: load_merge(path) for path in args.baseline}
    rows: dict[str, list[dict]] = {name: [] for name in merges}
    args.drives.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    mapper = args.out / "mapper.yaml"
    mapper.write_text(QUICK_MAPPER)
    for seed in (int(s) for s in args.seeds.split(",")):
        logs = simulate(args.drives, args.seconds, seed, visits)
        job = args.out / f"seed{seed}"
        run_fleet(logs, job, args.workers, mapper, reuse=True)
        store = TileStore(job)
        ids = {json.loads((p / "drive.json").read_text())["logs"][0]: p.name for p in (job / "journal").iterdir()}
        gts = [log.with_name(log.stem + ".gt.npz") for log in logs]
        tracks = {v: np.load(g)["trajectory_position_enu"] for v, g in zip(visits, gts, strict=True)}
        for (va, la), (vb, lb) in itertools.combinations(zip(visits, logs, strict=True), 2):
            def truth_of(mosaic, gt=gts[0], near=(tracks[va], tracks[vb])):  # near the pair's own tracks
                return Truth(gt, mosaic, list(near))

            for name, merge in merges.items():
                row = pair_scores(merge, store, truth_of, (ids[str(la)], ids[str(lb)]))
                row |= {"seed": seed, "visits": [va, vb]}
                rows[name].append(row)
                m, ds = row["merged"], list(row["drives"].values())
                print(f"{name:8s} seed {seed:2d} visits {va},{vb}: coverage {m['coverage']:.3f} "
                      f"(drives {ds[0]['coverage']:.3f} {ds[1]['coverage']:.3f}); mIoU reg "
                      f"{m['miou_pct_registered']:.1f} ({ds[0]['miou_pct_registered']:.1f} "
                      f"{ds[1]['miou_pct_registered']:.1f}); MAE reg {m['elev_mae_cm_registered']:.2f} cm "
                      f"({ds[0]['elev_mae_cm_registered']:.2f} {ds[1]['elev_mae_cm_registered']:.2f})",
                      file=sys.stderr, flush=True)
    result = {name: {"merged_less_better_drive": summary(r, "merged"),
                     "merged_on_best_cells_less_better_drive": summary(r, "merged_on_best_cells"), "pairs": r}
              for name, r in rows.items()}
    print(json.dumps(result | {"wall_s": time.perf_counter() - started}, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
