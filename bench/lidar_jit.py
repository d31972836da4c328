"""What compiling the vendor decoders' loops costs (drivers/lidar/compiled_loops.py), each case in a fresh process:
the import of the Lidar model table (numba's import included: the driver process's start-up cost; its `check`
compiles nothing), and per vendor the first decode call (compiling, or loading from the cache) beside the second.
Cases: `cold` (an empty cache folder, NUMBA_CACHE_DIR), `warm` (the same folder again), `no_cache` (numba finds no
folder it may write: compiled in each process). The first compiled call of a process also pays numba's own start
(the Velodyne's, timed first: with a warm cache its load is that start).

Run: .venv/bin/python bench/lidar_jit.py [--quick]. Last line: JSON {case: {import_s, vendor: {first_s, second_s}}}."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NEBULA = "/work/shared/data/lidar_nebula"

_CASE = """
import json, sys, time
if sys.argv[1] == "no_cache":
    import numba.core.caching
    numba.core.caching.CacheImpl._locator_classes = []  # as where no cache folder can be written
start = time.perf_counter()
from drivers.lidar.lidar_models import VENDOR_LIDARS  # noqa: F401, what the driver process imports
import_s = time.perf_counter() - start
from drivers.lidar.hesai_decoder import hesai_decoder
from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.robosense_decoder import robosense_decoder
from drivers.lidar.velodyne_decoder import velodyne_decoder
N = sys.argv[2]
cases = {
    "velodyne-vls128": (velodyne_decoder("velodyne-vls128", N + "/calib/VLS128.yaml"), N + "/velodyne/vls128.pcap"),
    "hesai-pandarqt128": (hesai_decoder("hesai-pandarqt128", N + "/calib/PandarQT128.csv"), N + "/hesai/qt128.pcap"),
    "robosense-helios16p": (robosense_decoder("robosense-helios16p", N + "/calib/RobosenseHelios16P.csv"),
                            N + "/robosense/helios16P.pcap"),
}
figures = {"import_s": round(import_s, 3)}
for model, (decoder, capture) in cases.items():
    payloads = [d.payload for d in read_pcap_udp(capture).datagrams][:200]
    times = []
    for _ in range(2):
        start = time.perf_counter()
        decoder.decode(payloads)
        times.append(time.perf_counter() - start)
    figures[model] = {"first_s": round(times[0], 3), "second_s": round(times[1], 4)}
print(json.dumps(figures))
"""


def run_case(case: str, cache_dir: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", _CASE, case, NEBULA], env=env, cwd=ROOT, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="accepted for the bench convention; the run is short")
    parser.parse_args()
    with tempfile.TemporaryDirectory() as cache_dir:
        results = {case: run_case(case, cache_dir) for case in ("cold", "warm", "no_cache")}
    for case, figures in results.items():
        vendors = ", ".join(f"{m} first {f['first_s']:.2f} s / second {f['second_s'] * 1e3:.1f} ms"
                            for m, f in figures.items() if m != "import_s")
        print(f"{case:9s} import {figures['import_s']:.2f} s; {vendors}")
    print(json.dumps(results))


if __name__ == "__main__":
    main()
