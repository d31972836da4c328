"""Camera-only held-out PSNR of the KITTI drives over model seeds, for the mapper as configured and with
fast-fit settings changed (`--set name=value`, mapper.fast_fit fields), mapped in-process one after the other
(as bench/kitti_error.py: 01 with its recorded poses, 0005 with its INS poses, maskless).

    .venv/bin/python bench/kitti_seeds.py [--quick] [--seeds 0,1,2,3] [--drive 01|0005|both] \
        --set photometric_patch_m=0.4

The last line is one JSON object: per drive and variant, the PSNR per seed and its mean.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from kitti_error import DATA, DRIVES, ROADLOG, mapped_once, with_seed  # noqa: E402

from mapping.offline.reconstruct_command import config_from_logs  # noqa: E402


def with_fast_fit(config, changes: dict):
    mapper = config.mapper
    return config.model_copy(update={"mapper": mapper.model_copy(
        update={"fast_fit": mapper.fast_fit.model_copy(update=changes)})})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--drive", choices=("01", "0005", "both"), default="both")
    parser.add_argument("--set", action="append", default=[], help="mapper.fast_fit NAME=VALUE (float)")
    parser.add_argument("--quick", action="store_true", help="01 and seed 0 only")
    args = parser.parse_args()
    seeds = [0] if args.quick else [int(s) for s in args.seeds.split(",")]
    drive = "01" if args.quick else args.drive
    changes = {k: float(v) for k, v in (s.split("=") for s in args.set)}
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in (("01", "0005") if drive == "both" else (drive,)):
            fmt, folder, extra = DRIVES[name]
            log = Path(tmp) / f"{folder}.mcap"
            subprocess.run([ROADLOG, "import", fmt, str(DATA / folder), "--out", str(log), *extra], check=True,
                           capture_output=True)
            config, config_path = config_from_logs([str(log)])
            for variant, cfg in (("main", config), ("changed", with_fast_fit(config, changes))):
                if variant == "changed" and not changes:
                    continue
                psnr = []
                for seed in seeds:
                    result, _, _ = mapped_once(log, with_seed(cfg, seed), config_path)
                    psnr.append(round(result.metrics["psnr_db"], 2))
                    print(f"{name} {variant} seed {seed}: {psnr[-1]:.2f} dB (train "
                          f"{result.metrics['psnr_train_db']:.2f}, wall {result.metrics.get('wall_s', 0) or 0:.0f} s)",
                          flush=True)
                out[f"{name}/{variant}"] = {"psnr_db": psnr, "mean": round(float(np.mean(psnr)), 3)}
                print(f"{name} {variant}: mean {np.mean(psnr):.3f} dB", flush=True)
    print(json.dumps({"changes": changes, **out}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
