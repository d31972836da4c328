"""Ablation bench: the paper's Table 3 and its RoMe baseline on simulated `city` and `ramp` drives.

Runs `roadlog reconstruct` (default fast path, with the ground truth) for the full model and every
`--ablation`, on both scenarios, plus the ramp without Lidar; prints a markdown table and writes it to
--table; the last line is JSON with every run's metrics and the paper's effects checked:
explicit RGB loses >= 3 dB on city, no elevation MLP at least doubles the ramp's Elev-error, RoMe fails
on the ramp (Elev-error > 20 cm). Drives are cached under /tmp/maplab/.

    .venv/bin/python bench/ablation.py [--quick] [--seconds 30.5] [--table PATH]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
from pathlib import Path

_spec = importlib.util.spec_from_file_location("mapping_bench", Path(__file__).with_name("mapping.py"))
mapping_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(mapping_bench)

ABLATIONS = ("no-elevation-mlp", "no-colour-mlps", "embedding", "no-semantics", "rome")
QUICK_RUNS = {"city": ("none", "no-colour-mlps"), "ramp": ("none", "no-elevation-mlp", "rome", "no-lidar")}


def fmt(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 s drives, only the runs the effects need")
    parser.add_argument("--seconds", type=float, default=30.5)
    parser.add_argument("--table", type=Path, default=Path("/tmp/maplab/ablation.md"))
    args = parser.parse_args()
    seconds = 3.0 if args.quick else args.seconds
    results: dict[str, dict[str, dict]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for scenario in ("city", "ramp"):
            log = mapping_bench.drive(scenario, seconds)
            runs = QUICK_RUNS[scenario] if args.quick else ("none", *ABLATIONS) + (("no-lidar",) if scenario == "ramp"
                                                                                  else ())
            for name in runs:
                extra = {"none": (), "no-lidar": ("--no-lidar",)}.get(name, ("--ablation", name))
                m = mapping_bench.run(log, Path(tmp) / f"{scenario}-{name}", *extra)
                results.setdefault(scenario, {})[name] = m
                print(scenario, name, json.dumps(m), flush=True)
    lines = [f"Ablations, simulated drives of {seconds:g} s (fast path, seeded scenarios)", "",
             "| scenario | run | PSNR (dB) | mIoU (%) | Elev-error (cm) | elev MAE vs truth (cm) | rtf |",
             "|---|---|---|---|---|---|---|"]
    for scenario, runs in results.items():
        for name, m in runs.items():
            lines.append(f"| {scenario} | {name} | {fmt(m['psnr_db'])} | {fmt(m['miou_pct'])} | "
                         f"{fmt(m['elev_error_cm'])} | {fmt(m['elev_mae_gt_cm'])} | {fmt(m['rtf'])} |")
    table = "\n".join(lines)
    print(table)
    args.table.parent.mkdir(parents=True, exist_ok=True)
    args.table.write_text(table + "\n")
    city, ramp = results["city"], results["ramp"]
    effects = {
        "explicit_rgb_loss_db": city["none"]["psnr_db"] - city["no-colour-mlps"]["psnr_db"],
        "no_elevation_mlp_ratio": ramp["no-elevation-mlp"]["elev_error_cm"] / ramp["none"]["elev_error_cm"],
        "rome_ramp_elev_error_cm": ramp["rome"]["elev_error_cm"],
    }
    effects["effects_hold"] = (effects["explicit_rgb_loss_db"] >= 3.0 and effects["no_elevation_mlp_ratio"] >= 2.0
                               and effects["rome_ramp_elev_error_cm"] > 20.0)
    print(json.dumps({"seconds": seconds, **effects, "runs": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
