"""Pose-noise bench (issue 17 item 5): what injected pose error costs the map, with and without pose refinement.

On N random worlds (`roadlog simulate --scenario random --seed S`, as bench/worlds.py) each drive is mapped by
`roadlog reconstruct --gt`, with Lidar and with `--no-lidar`: with the poses as fused (`exact`), with a
smooth random pose error injected into the trajectory (`--pose-noise-m`, `--pose-noise-deg`: independent draws every
`--every-s`, linear between; mapping/localization/pose_noise.py) without refinement (`noisy`), and the same with
`--pose-refinement on` (`refined`); with Lidar also with `--pose-refinement photometric` (`photometric`: no Lidar
ground registration first), the refinement before the registration, side by side, and with `--pose-refinement
lidar` (`lidar`: every axis from the Lidar ground, heights and intensity contrast, the drive read again with the
corrected trajectory); and with the exact poses and `--pose-refinement on` / `lidar` (`--clean-refined`:
`clean_refined`, `clean_lidar`: the refinement must not make a good map worse). Reported per run and as
median / worst over the worlds: held-out PSNR, bird's-eye mIoU, lane-marking IoU, the costs against `exact` (dB,
points), the vehicle pose's RMS error at the keyframes before and after refinement, and the wall times. The target
(issue 17): 10-20 cm RMS pose noise costs at most 3 points of mIoU and 1 dB of PSNR. The last line is one JSON
object.

    .venv/bin/python bench/pose_noise.py [--quick] [--worlds 3] [--seconds 6] [--noise-m 0.2] [--noise-deg 0.1]
        [--every-s 0.5] [--modes lidar no_lidar] [--runs noisy refined photometric lidar ...]
        [--noise-seed-per-world] [--drives DIR] [--noise-at poses|fixes] [--fix-tau-s 10]
        [--fix-white-fraction 0.2] [--fix-vertical-ratio 1.5] [--registered]

`--noise-at fixes` (bench/pose_noise_fixes.py): instead of an error injected into the fused poses, the log's GNSS
fixes are perturbed before the fusion (a copy of the drive, its fixes only: per axis a Gauss-Markov error with
time constant --fix-tau-s plus white noise, 3-D RMS --noise-m, the vertical --fix-vertical-ratio times each
horizontal axis, the fixes' covariance that sigma; the receiver's Doppler velocities as logged), so the fused poses
carry what the fusion leaves of a receiver's error; the fused track's error against the truth is reported per world
(RMS, its common shift along / across the track and rigid turn, the non-rigid rest). The noisy runs map the
perturbed drive; `exact`, `clean_refined` and `clean_lidar` the drive as simulated (RTK fixes). `--registered` adds
each map's raster mIoU as placed and registered (moved by the shift that overlays it best on the truth, bench/
fleet.py's): an evaluation lens, not the target.

Each run with refinement also reports what is left of the error as its mean over the keyframes (common along /
across the track) and the turn of the whole drive (a shift and a turn of all of it, which a registration of the
drive against itself cannot see), and the RMS left without them (non-rigid).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import tempfile
import time
from pathlib import Path

_spec = importlib.util.spec_from_file_location("worlds_bench", Path(__file__).with_name("worlds.py"))
worlds_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(worlds_bench)

_spec = importlib.util.spec_from_file_location("pose_noise_fixes", Path(__file__).with_name("pose_noise_fixes.py"))
fixes_bench = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = fixes_bench  # its dataclass looks its module up
_spec.loader.exec_module(fixes_bench)

summarise, fmt = worlds_bench.summarise, worlds_bench.fmt  # median and worst over the worlds; a figure
MODES = {"lidar": (), "no_lidar": ("--no-lidar",)}
FIGURES = ("psnr_db", "miou_pct", "lane_marking_iou_pct", "wall_s")


def run(log: Path, out: Path, noise: tuple[str, ...], *extra: str) -> dict:
    figures = worlds_bench.reconstruct(log, out, *noise, *extra)
    if REGISTERED:
        figures.update(fixes_bench.registered_miou(out, log.with_suffix(".gt.npz")))
    m = json.loads((out / "metrics.json").read_text())
    pose = m.get("pose_noise") or {}
    return {**{k: figures[k] for k in FIGURES},
            "pose_error_before_cm": (pose.get("keyframes_before") or {}).get("position_rms_cm"),
            "pose_error_after_cm": (pose.get("keyframes_after") or {}).get("position_rms_cm"),
            "rotation_error_before_deg": (pose.get("keyframes_before") or {}).get("rotation_rms_deg"),
            "rotation_error_after_deg": (pose.get("keyframes_after") or {}).get("rotation_rms_deg"),
            "pose_refinement_wall_s": m.get("pose_refinement_wall_s") or m.get("lidar_pre_pass_wall_s"),
            "pose_error_after": (pose.get("keyframes_after") or {}) or None,
            **{k: figures[k] for k in ("miou_pct_raster", "miou_pct_registered", "fleet_shift_to_truth_cm",
                                       "shift_to_truth_cm") if k in figures}}


RUNS = ("noisy", "refined", "photometric", "lidar", "clean_refined", "clean_lidar")
ONLY: tuple[str, ...] = RUNS  # --runs: those mapped besides `exact`
REGISTERED = False  # --registered: each map's mIoU also after its best 2-D shift onto the truth
COSTS = (("psnr_cost_db", "psnr_db"), ("miou_cost_pts", "miou_pct"))
REGISTERED_COSTS = (("raster_miou_cost_pts", "miou_pct_raster"), ("registered_miou_cost_pts", "miou_pct_registered"))


def noisy_runs(mode: str, clean: bool) -> tuple[str, ...]:
    """The runs of a mode besides `exact` (all but clean_refined with the noise injected), of those --runs asks."""
    runs = (("noisy", "refined") + (("photometric", "lidar") if mode == "lidar" else ())
            + (("clean_refined",) if clean else ()) + (("clean_lidar",) if clean and mode == "lidar" else ()))
    return tuple(r for r in runs if r in ONLY)


def every_run(results: list[dict], modes: list[str], clean: bool):
    """(world's result, mode, run name, its figures) for every run of every world, the exact one first."""
    for r in results:
        for mode in modes:
            for name in ("exact", *noisy_runs(mode, clean)):
                yield r, mode, name, r[mode][name]


def perturbed_fixes_log(log: Path, fix_noise) -> tuple[Path, dict]:
    """The drive `log` with its GNSS fixes perturbed (bench/pose_noise_fixes.py), kept beside it with its truth."""
    n = fix_noise
    noisy = log.with_name(f"{log.stem}_fixes{100 * n.position_rms_m:g}cm_tau{n.tau_s:g}s_w{n.white_fraction:g}"
                          f"_v{n.vertical_ratio:g}_seed{n.seed}.mcap")
    drawn = fixes_bench.perturb_log(log, noisy, n)
    truth = noisy.with_suffix(".gt.npz")
    if not truth.exists():
        truth.symlink_to(log.with_suffix(".gt.npz").resolve())
    return noisy, drawn


def world(seed: int, seconds: float, folder: Path, drives: Path, noise: tuple[str, ...], modes: dict,
          clean: bool, fix_noise=None) -> dict:
    """One world's runs; with `fix_noise` (--noise-at fixes) the noisy runs map the drive with its GNSS fixes
    perturbed before the fusion instead of an error injected into the fused poses."""
    log = drives / f"random_{seed}_{seconds:g}s.mcap"
    if not log.exists():
        worlds_bench.simulate("random", seed, seconds, log)
    result = {"seed": seed}
    noisy_log = log
    if fix_noise is not None:
        noisy_log, drawn = perturbed_fixes_log(log, fix_noise)
        gt = log.with_suffix(".gt.npz")
        result["fixes"] = {"drawn": drawn, "fused_error_exact_fixes": fixes_bench.fused_error(log, gt),
                           "fused_error_perturbed_fixes": fixes_bench.fused_error(noisy_log, gt)}
        print(json.dumps({"seed": seed, **result["fixes"]}), flush=True)
        noise = ()
    for mode, extra in modes.items():
        exact = run(log, folder / f"{seed}_{mode}_exact", (), *extra)
        runs = {"exact": exact}
        settings = {"noisy": (noise, "off"), "refined": (noise, "on"), "photometric": (noise, "photometric"),
                    "lidar": (noise, "lidar"), "clean_refined": ((), "on"), "clean_lidar": ((), "lidar")}
        for name in noisy_runs(mode, clean):
            injected, setting = settings[name]
            runs[name] = run(log if name.startswith("clean") else noisy_log, folder / f"{seed}_{mode}_{name}",
                             injected, *extra, "--pose-refinement", setting)
        costs = {f"{name}_{k}": (exact[figure] - r[figure]) if None not in (exact.get(figure), r.get(figure)) else None
                 for name, r in runs.items() if name != "exact"
                 for k, figure in COSTS + (REGISTERED_COSTS if REGISTERED else ())}
        result[mode] = {**runs, **costs}
        print(json.dumps({"seed": seed, "mode": mode, **result[mode]}), flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one world of 3 s, with Lidar only")
    parser.add_argument("--worlds", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--noise-m", type=float, default=0.2, help="RMS of the injected 3-D position error (m)")
    parser.add_argument("--noise-deg", type=float, default=0.1, help="RMS per rotation axis (degrees)")
    parser.add_argument("--every-s", type=float, default=0.5, help="the error's independent draws this far apart")
    parser.add_argument("--modes", nargs="+", choices=sorted(MODES), default=sorted(MODES),
                        help="with Lidar, camera-only (--no-lidar) or both")
    parser.add_argument("--clean-refined", action="store_true",
                        help="also map each drive with the exact poses and the refinement on (clean_refined)")
    parser.add_argument("--drives", type=Path, default=Path("/tmp/maplab/pose_noise"),
                        help="the simulated drives are kept here and reused")
    parser.add_argument("--noise-seed-per-world", action="store_true",
                        help="draw each world's error with its own seed (the world's); by default every world gets "
                             "the same draws (seed 0), so the worlds show one error along different roads")
    parser.add_argument("--runs", nargs="+", choices=RUNS, default=list(RUNS),
                        help="the runs besides `exact` (default: all that --modes and --clean-refined give)")
    parser.add_argument("--noise-at", choices=("poses", "fixes"), default="poses",
                        help="poses: the error injected into the fused poses (the default, as before); fixes: the "
                             "log's GNSS fixes perturbed before the fusion (bench/pose_noise_fixes.py: Gauss-Markov "
                             "plus white per axis, --noise-m the 3-D RMS, the fixes' covariance that sigma; the "
                             "receiver's velocities as logged), --noise-deg and --every-s unused")
    parser.add_argument("--fix-tau-s", type=float, default=10.0, help="fixes: the Gauss-Markov time constant (s)")
    parser.add_argument("--fix-white-fraction", type=float, default=0.2,
                        help="fixes: the share of each axis's variance that is white (per epoch)")
    parser.add_argument("--fix-vertical-ratio", type=float, default=1.5,
                        help="fixes: the vertical sigma over each horizontal axis's")
    parser.add_argument("--registered", action="store_true",
                        help="also each map's raster mIoU as placed and after its best rigid 2-D shift and turn onto "
                             "the truth (an evaluation lens: bench/pose_noise_fixes.registered_miou)")
    args = parser.parse_args()
    global ONLY, REGISTERED
    ONLY = tuple(args.runs)
    REGISTERED = args.registered
    count, seconds = (1, 3.0) if args.quick else (args.worlds, args.seconds)
    modes = {"lidar": MODES["lidar"]} if args.quick else {mode: MODES[mode] for mode in args.modes}
    noise = ("--pose-noise-m", str(args.noise_m), "--pose-noise-deg", str(args.noise_deg),
             "--pose-noise-every-s", str(args.every_s))
    args.drives.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        results = [world(args.first_seed + i, seconds, Path(tmp), args.drives,
                         noise + (("--pose-noise-seed", str(args.first_seed + i)) if args.noise_seed_per_world else ()),
                         modes, args.clean_refined,
                         fixes_bench.FixNoise(args.noise_m, args.fix_tau_s, args.fix_white_fraction,
                                              args.fix_vertical_ratio,
                                              args.first_seed + i if args.noise_seed_per_world else 0)
                         if args.noise_at == "fixes" else None)
                   for i in range(count)]
    stats = {}
    for mode in modes:
        names = noisy_runs(mode, args.clean_refined)
        stats[mode] = {
            **{f"{kind}_{k}": summarise([r[mode][f"{kind}_{k}"] for r in results], "low")
               for kind in names for k, _ in COSTS + (REGISTERED_COSTS if REGISTERED else ())},
            **{f"{run_name}_{k}": summarise([r[mode][run_name][k] for r in results],
                                            "low" if "error" in k or "wall" in k else "high")
               for run_name in ("exact", *names)
               for k in (*FIGURES, "pose_error_after_cm", "pose_refinement_wall_s")
               if not (run_name in ("exact", "noisy") and k in ("pose_error_after_cm", "pose_refinement_wall_s"))},
            **{f"{run_name}_{k}": summarise([(r[mode][run_name]["pose_error_after"] or {}).get(k) for r in results],
                                            "low")
               for run_name in names if run_name not in ("noisy", "clean_refined", "clean_lidar")
               for k in ("common_horizontal_cm", "relative_horizontal_rms_cm", "nonrigid_horizontal_rms_cm")},
        }
        if "noisy" in names:
            stats[mode]["pose_error_before_cm"] = summarise([r[mode]["noisy"]["pose_error_before_cm"]
                                                             for r in results], "low")
        s = stats[mode]
        for name in ("refined", "lidar"):
            if name in names:
                s[f"{name}_target_met"] = all(
                    s[f"{name}_{k}"]["worst"] is not None and s[f"{name}_{k}"]["worst"] <= bound
                    for k, bound in (("psnr_cost_db", 1.0), ("miou_cost_pts", 3.0)))
    if args.noise_at == "fixes":
        stats["fused_error_perturbed_fixes"] = {
            k: summarise([r["fixes"]["fused_error_perturbed_fixes"][k] for r in results], "low")
            for k in ("position_rms_cm", "horizontal_rms_cm", "common_horizontal_cm", "nonrigid_horizontal_rms_cm",
                      "yaw_rms_deg")}
        print("| world | fixes' error drawn: 3-D / horizontal / vertical RMS cm | fused track, exact fixes: 3-D / "
              "horizontal RMS cm | fused track, perturbed fixes: 3-D / horizontal / vertical RMS cm | of it common "
              "along / across cm, rigid turn deg, non-rigid RMS cm | yaw RMS deg |")
        print("|---|---|---|---|---|---|")
        for r in results:
            d, e, p = (r["fixes"][k] for k in ("drawn", "fused_error_exact_fixes", "fused_error_perturbed_fixes"))
            print(f"| {r['seed']} | {fmt(d['error_rms_cm'])} / {fmt(d['horizontal_rms_cm'])} / "
                  f"{fmt(d['vertical_rms_cm'])} | {fmt(e['position_rms_cm'])} / {fmt(e['horizontal_rms_cm'])} | "
                  f"{fmt(p['position_rms_cm'])} / {fmt(p['horizontal_rms_cm'])} / {fmt(p['vertical_rms_cm'])} | "
                  f"{fmt(p['common_along_cm'])} / {fmt(p['common_across_cm'])}, {fmt(p['rigid_turn_deg'])}, "
                  f"{fmt(p['nonrigid_horizontal_rms_cm'])} | {fmt(p['yaw_rms_deg'])} |")
    if REGISTERED:
        print("| world | mode | run | raster mIoU % placed / registered | the map's shift onto the truth cm (e, n): "
              "fleet's, polished on the score |")
        print("|---|---|---|---|---|")
        for r, mode, name, f in every_run(results, modes, args.clean_refined):
            print(f"| {r['seed']} | {mode} | {name} | {fmt(f['miou_pct_raster'])} / "
                  f"{fmt(f['miou_pct_registered'])} | {fmt(f['fleet_shift_to_truth_cm'][0])}, "
                  f"{fmt(f['fleet_shift_to_truth_cm'][1])}; {fmt(f['shift_to_truth_cm'][0])}, "
                  f"{fmt(f['shift_to_truth_cm'][1])} |")
    print("| world | mode | run | PSNR dB | mIoU % | lane marking IoU % | pose error cm | common along / across cm, "
          "turn deg, non-rigid cm | wall s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r, mode, name, f in every_run(results, modes, args.clean_refined):
        error = f["pose_error_before_cm"] if name == "noisy" else f["pose_error_after_cm"]
        after = f["pose_error_after"] or {}
        print(f"| {r['seed']} | {mode} | {name} | {fmt(f['psnr_db'])} | {fmt(f['miou_pct'])} | "
              f"{fmt(f['lane_marking_iou_pct'])} | {fmt(error if name != 'exact' else 0.0)} | "
              f"{fmt(after.get('common_along_cm'))} / {fmt(after.get('common_across_cm'))}, "
              f"{fmt(after.get('rigid_turn_deg'))}, {fmt(after.get('nonrigid_horizontal_rms_cm'))} | "
              f"{fmt(f['wall_s'])} |")
    for mode in modes:
        s = stats[mode]
        for name in noisy_runs(mode, args.clean_refined):
            line = (f"{mode}, {name}: PSNR cost median {fmt(s[f'{name}_psnr_cost_db']['median'])} worst "
                    f"{fmt(s[f'{name}_psnr_cost_db']['worst'])} dB; mIoU cost median "
                    f"{fmt(s[f'{name}_miou_cost_pts']['median'])} worst {fmt(s[f'{name}_miou_cost_pts']['worst'])} "
                    f"points")
            if REGISTERED:
                line += (f"; registered (lens) mIoU cost median {fmt(s[f'{name}_registered_miou_cost_pts']['median'])}"
                         f" worst {fmt(s[f'{name}_registered_miou_cost_pts']['worst'])} points (raster as placed "
                         f"{fmt(s[f'{name}_raster_miou_cost_pts']['median'])} / "
                         f"{fmt(s[f'{name}_raster_miou_cost_pts']['worst'])})")
            if f"{name}_common_horizontal_cm" in s:
                line += (f"; pose error after {fmt(s[f'{name}_pose_error_after_cm']['median'])} / "
                         f"{fmt(s[f'{name}_pose_error_after_cm']['worst'])} cm, of it common "
                         f"{fmt(s[f'{name}_common_horizontal_cm']['median'])} / "
                         f"{fmt(s[f'{name}_common_horizontal_cm']['worst'])}, relative "
                         f"{fmt(s[f'{name}_relative_horizontal_rms_cm']['median'])} / "
                         f"{fmt(s[f'{name}_relative_horizontal_rms_cm']['worst'])}, non-rigid "
                         f"{fmt(s[f'{name}_nonrigid_horizontal_rms_cm']['median'])} / "
                         f"{fmt(s[f'{name}_nonrigid_horizontal_rms_cm']['worst'])} cm horizontal")
            if f"{name}_target_met" in s:
                line += f": target {'met' if s[f'{name}_target_met'] else 'not met'}"
            print(line)
    print(json.dumps({"bench": "pose_noise", "noise_at": args.noise_at, "registered": REGISTERED,
                      **({"fix_tau_s": args.fix_tau_s, "fix_white_fraction": args.fix_white_fraction,
                          "fix_vertical_ratio": args.fix_vertical_ratio} if args.noise_at == "fixes" else {}),
                      "worlds": count, "seconds": seconds, "noise_m": args.noise_m,
                      "noise_deg": args.noise_deg, "every_s": args.every_s,
                      "noise_seed": "per world" if args.noise_seed_per_world else 0,
                      "cpus_available": len(os.sched_getaffinity(0)), "load_average_1min": os.getloadavg()[0],
                      "wall_s": round(time.perf_counter() - started, 1), "median_worst": stats, "runs": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
