"""Where a camera-only map of a real drive loses its held-out PSNR: the KITTI drives in ../shared/data imported and
mapped in-process (maskless, camera only, as bench/kitti.py --quick), then the held-out and training views broken
down, one line or table each:

- per held-out view: PSNR, bias (mean render - image), contrast (std render / std image);
- pooled over the held-out views: share of pixels, share of the squared error, PSNR and bias by distance from the
  camera, image row, observed brightness; the share of the error the worst 1 / 5 / 10 % of pixels carry;
- what the 10 cm mesh could hold, on the map's own surface: each held-out view's vertex colours fitted (least
  squares) to that view alone (the resolution ceiling), the fast fit's per-vertex targets rendered as they are
  (what the colour codes and decoders lose), and one colour per vertex fitted to all the training views at once,
  without and with a gain per view (how far the training views agree with each other on this surface);
- the PSNR over `--seeds` model seeds (mapper.model.seed: the colour fit and the elevation MLP's start).

    .venv/bin/python bench/kitti_error.py [--quick] [--drive 01|0005|both] [--seeds 0,1,2,3]

The last line is one JSON object (per drive: held-out and training PSNR, the ceilings above, the seeds' PSNR).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import lsqr

ROOT = Path(__file__).resolve().parents[1]
ROADLOG = str(ROOT / ".venv" / "bin" / "roadlog")
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(ROOT))

import mapping.fits.fast_fit as fast_fit  # noqa: E402
from mapping.fits.reconstruction import select_keyframes  # noqa: E402
from mapping.method.road_map import WindowIndex, view_rgb  # noqa: E402
from mapping.offline.reconstruct_command import config_from_logs, run_reconstruction  # noqa: E402
from mapping.outputs.map_metrics import _view_seen  # noqa: E402

DRIVES = {"01": ("kitti-odometry", "kitti_odometry_01", ()),
          "0005": ("kitti-raw", "kitti_raw_0005", ("--poses", "oxts"))}
HOLDOUT_EVERY = 10  # as mapping.fits.reconstruction.reconstruct's default
DAMP = 0.02  # the least-squares fits' damping (a vertex few pixels see stays near 0 rather than ringing)


def db(mse: float) -> float:
    return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))


def with_seed(config, seed: int):
    mapper = config.mapper
    return config.model_copy(update={"mapper": mapper.model_copy(
        update={"model": mapper.model.model_copy(update={"seed": seed})})})


def mapped_once(log: Path, config, config_path: Path):
    """The map (camera only) and the fast fit's vertex observations (the colour targets)."""
    stash = {}
    fit_colour = fast_fit.fit_colour

    def keeping(road_map, obs, *args, **kwargs):
        stash["obs"] = obs
        return fit_colour(road_map, obs, *args, **kwargs)

    fast_fit.fit_colour = keeping
    try:
        with tempfile.TemporaryDirectory() as out:
            result, drive = run_reconstruction([str(log)], Path(out), config, config_path, use_lidar=False,
                                               progress=False)
    finally:
        fast_fit.fit_colour = fit_colour
    return result, drive, stash["obs"]


def view_rows(road_map, drive, config, keyframes):
    """Per view: the evaluated pixels' triangles, weights, grey image and grey render, flat pixel index, the
    sampled grid's shape and the distance to the surface."""
    windows = WindowIndex.of(road_map.mesh)
    mapped = (road_map.observed[road_map.mesh.faces] > 0).all(1)
    w = config.mapper.windows
    rows = []
    for kf in keyframes:
        seen = _view_seen(road_map, drive.cameras, kf, drive.path, w.before_m, w.after_m, windows, mapped)
        g = seen.geometry
        road = seen.road_pixels.ravel()[g.hit]
        pix = np.flatnonzero(g.hit)[road]
        rows.append({"tri": g.tri[road], "w": g.weights.numpy()[road],
                     "obs": seen.observed.reshape(-1, 3)[g.hit][road].mean(1),
                     "rend": view_rgb(road_map, g, seen.camera).reshape(-1, 3)[g.hit][road].mean(1),
                     "pix": pix, "shape": g.shape, "dist": seen.distance_m.ravel()[pix]})
    return rows


def design(rows, ids=None):
    """The sparse (pixels x vertices) barycentric matrix of `rows`, and its vertex ids."""
    tri = np.concatenate([r["tri"] for r in rows])
    wt = np.concatenate([r["w"] for r in rows])
    ids, inv = np.unique(tri, return_inverse=True)
    a = sp.csr_matrix((wt.ravel(), (np.repeat(np.arange(len(tri)), 3), inv.ravel())), shape=(len(tri), len(ids)))
    return a, ids


def table(name, key, edges, se, bias):
    total = se.sum()
    print(f"  by {name}: " + "; ".join(
        f"{lo:g}-{hi:g}: px {100 * s.mean():.1f} %, err {100 * se[s].sum() / total:.1f} %, {db(se[s].mean()):.2f} dB, "
        f"bias {bias[s].mean():+.3f}"
        for lo, hi in zip(edges[:-1], edges[1:], strict=False) if (s := (key >= lo) & (key < hi)).any()))


def analyse(name: str, log: Path, seeds: list[int], ceilings: bool = True) -> dict:
    config, config_path = config_from_logs([str(log)])
    result, drive, obs = mapped_once(log, config, config_path)
    m, road_map = result.metrics, result.road_map
    selected = select_keyframes(drive.keyframes, drive.path, config.mapper.inputs.keyframe_spacing_m)
    held = [k for i, k in enumerate(selected) if i % HOLDOUT_EVERY == HOLDOUT_EVERY // 2]
    train = [k for i, k in enumerate(selected) if i % HOLDOUT_EVERY != HOLDOUT_EVERY // 2]
    print(f"{name}: held-out PSNR {m['psnr_db']:.2f} dB on {len(held)} views, train {m['psnr_train_db']:.2f}, "
          f"bands {m['psnr_by_distance_db']}")
    H, T = view_rows(road_map, drive, config, held), view_rows(road_map, drive, config, train)
    for i, r in enumerate(H):
        e = r["rend"] - r["obs"]
        print(f"  held-out view {i}: {db((e ** 2).mean()):.2f} dB, {len(e)} px, bias {e.mean():+.3f}, "
              f"contrast {r['rend'].std() / r['obs'].std():.2f}")
    rend, o = np.concatenate([r["rend"] for r in H]), np.concatenate([r["obs"] for r in H])
    se, bias = (rend - o) ** 2, rend - o
    table("distance (m)", np.concatenate([r["dist"] for r in H]), [0, 5, 10, 15, 20, 30, 40, np.inf], se, bias)
    table("image row (fraction of height)", np.concatenate([r["pix"] // r["shape"][1] / r["shape"][0] for r in H]),
          np.linspace(0.4, 1.0, 7), se, bias)
    table("image grey level", o, [0, .1, .2, .3, .4, .5, .6, .8, 1.01], se, bias)
    worst = np.cumsum(np.sort(se)[::-1]) / se.sum()
    print("  the worst 1 / 5 / 10 % of pixels carry " + " / ".join(
        f"{100 * worst[int(f * len(se))]:.0f}" for f in (0.01, 0.05, 0.1)) + " % of the squared error")
    alone = []
    for r in H:
        a, _ = design([r])
        alone.append(db(((a @ lsqr(a, r["obs"], damp=DAMP)[0] - r["obs"]) ** 2).mean()))
    target = obs.colour_mean(np.arange(road_map.mesh.num_vertices)).mean(2)  # (N, cameras) grey
    cams = sorted(drive.cameras)

    def as_target(rows, views):
        return np.mean([db((((target[r["tri"], cams.index(k.camera)] * r["w"]).sum(1) - r["obs"]) ** 2).mean())
                        for r, k in zip(rows, views, strict=True)])

    if not ceilings:  # --quick: the fits to all the training views at once are most of the analysis's time
        print(f"  ceilings: each held-out view fitted alone {np.mean(alone):.2f} dB; the fit's per-vertex targets "
              f"rendered: held-out {as_target(H, held):.2f} dB (the map: {m['psnr_db']:.2f}); the training views' "
              "joint fits: not in --quick")
        return {"psnr_db": round(m["psnr_db"], 2), "psnr_train_db": round(m["psnr_train_db"], 2),
                "worst_5pct_error_share": round(float(worst[int(0.05 * len(se))]), 3),
                "held_out_view_alone_db": round(float(np.mean(alone)), 2),
                "per_vertex_targets_held_out_db": round(float(as_target(H, held)), 2)}
    a, ids = design(T)
    ot = np.concatenate([r["obs"] for r in T])
    view = np.concatenate([np.full(len(r["obs"]), k) for k, r in enumerate(T)])
    joint = lsqr(a, ot, damp=DAMP, iter_lim=300)[0]
    gain = np.ones(len(T))
    for _ in range(4):  # a gain per training view and the colours, alternately
        colours = lsqr(sp.diags(gain[view]) @ a, ot, damp=DAMP, iter_lim=300)[0]
        pred = a @ colours
        gain = np.bincount(view, pred * ot) / np.bincount(view, pred * pred)
        gain /= np.exp(np.log(gain).mean())

    def mean_view_db(pred):
        return np.mean([db(((pred[view == k] - ot[view == k]) ** 2).mean()) for k in range(len(T))])

    print(f"  ceilings: each held-out view fitted alone {np.mean(alone):.2f} dB; the fit's per-vertex targets "
          f"rendered: held-out {as_target(H, held):.2f}, train {as_target(T, train):.2f} dB (the map: "
          f"{m['psnr_db']:.2f} / {m['psnr_train_db']:.2f}); one colour per vertex fitted to every training view: "
          f"train {mean_view_db(a @ joint):.2f} dB, with a gain per view {mean_view_db(gain[view] * pred):.2f} dB "
          f"(gains {gain.min():.2f}-{gain.max():.2f})")
    print("  training views' bias (render - image), in time order: "
          + " ".join(f"{(r['rend'] - r['obs']).mean():+.3f}" for r in T))
    figures = {"psnr_db": round(m["psnr_db"], 2), "psnr_train_db": round(m["psnr_train_db"], 2),
               "worst_5pct_error_share": round(float(worst[int(0.05 * len(se))]), 3),
               "held_out_view_alone_db": round(float(np.mean(alone)), 2),
               "per_vertex_targets_held_out_db": round(float(as_target(H, held)), 2),
               "one_colour_all_training_views_db": round(float(mean_view_db(a @ joint)), 2),
               "with_view_gains_db": round(float(mean_view_db(gain[view] * pred)), 2)}
    if seeds:
        by_seed = []
        for seed in seeds:
            s_result, _, _ = mapped_once(log, with_seed(config, seed), config_path)
            by_seed.append(s_result.metrics["psnr_db"])
        print(f"  model seeds {seeds}: held-out PSNR " + " / ".join(f"{f:.2f}" for f in by_seed)
              + f" dB (mean {np.mean(by_seed):.2f}, range {max(by_seed) - min(by_seed):.2f})")
        figures["psnr_db_by_seed"] = [round(f, 2) for f in by_seed]
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--drive", choices=("01", "0005", "both"), default="both")
    parser.add_argument("--seeds", default="", help="comma-separated model seeds to map again (e.g. 0,1,2,3)")
    parser.add_argument("--quick", action="store_true",
                        help="01 only, one seed, without the training views' joint fits (42 s at a load of 6)")
    args = parser.parse_args()
    seeds = [] if args.quick else [int(s) for s in args.seeds.split(",") if s]
    drives = ("01",) if args.quick else ("01", "0005") if args.drive == "both" else (args.drive,)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in drives:
            fmt, folder, extra = DRIVES[name]
            log = Path(tmp) / f"{folder}.mcap"
            subprocess.run([ROADLOG, "import", fmt, str(DATA / folder), "--out", str(log), *extra], check=True,
                           capture_output=True)
            out[name] = analyse(name, log, seeds, ceilings=not args.quick)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
