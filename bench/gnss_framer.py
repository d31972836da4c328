"""CPU cost of the GNSS stream framer (drivers/gnss/stream_framer.py) on real and on hostile byte streams.

Each stream is fed in reads of READ_BYTES, as the serial driver gets them, and its cost is given in CPU seconds
per second of input at 460800 baud (46,080 bytes/s): the real u-blox logs of /work/shared/data/gnss_pyubx2, and
streams made to cost the most: false UBX headers (a UBX sync, a real class, a claimed length up to the maximum,
every 8 bytes; and every 6 bytes each claiming the maximum, so that one waits for 8 KiB at every read), a flood of
UBX syncs, a flood of '$', short NMEA sentences with bad checksums, the shortest candidates one after another ("$\n",
"$" cut short by a UBX sync, "\xb5$"), sentences cut short behind a false header that holds 8 KiB in the buffer,
random bytes.
`worst_over_real` is the costliest hostile stream over the real one (the aim: within 10x).

    python bench/gnss_framer.py [--quick] [--baseline OLD_STREAM_FRAMER.py]

Last line: JSON {stream: {bytes, cpu_s_per_s, frames, rejected}, worst_over_real} (with --baseline: that for
`framer` and for `baseline`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import random
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from daemon.spine.health import HealthCounters  # noqa: E402 (after the path)

DATA = Path("/work/shared/data/gnss_pyubx2")
BYTES_PER_S = 460_800 // 10  # 8N1: ten bits a byte
READ_BYTES = 64


def real_stream() -> bytes:
    return b"".join(p.read_bytes() for p in sorted(DATA.glob("*")) if p.suffix in (".ubx", ".log"))


def hostile_streams(n: int, rng: random.Random) -> dict[str, bytes]:
    false_headers = bytearray()
    while len(false_headers) < n:
        length = rng.randrange(0, 8193)
        false_headers += b"\xb5\x62\x01" + bytes((rng.randrange(256), length & 0xFF, length >> 8)) + rng.randbytes(2)
    def repeated(unit: bytes) -> bytes:
        return (unit * (n // len(unit) + 1))[:n]

    return {
        "false_ubx_headers": bytes(false_headers[:n]),
        "max_ubx_headers_every_6": repeated(b"\xb5\x62\x01\x07\xff\x1f"),
        "sentences_behind_a_false_header": repeated(b"\xb5\x62\x01\x07\x00\x20" + b"$A" * 29),
        "dollar_newline": repeated(b"$\n"),
        "dollar_before_ubx_sync": repeated(b"$\xb5\x62"),
        "b5_dollar": repeated(b"\xb5$"),
        "tiny_bad_checksum_sentences": repeated(b"$*01\n"),
        "ubx_sync_flood": b"\xb5\x62" * (n // 2),
        "dollar_flood": b"$" * n,
        "bad_checksum_sentences": b"$A*00\r\n" * (n // 7),
        "random_bytes": rng.randbytes(n),
    }


def load_framer(path: Path | None):
    if path is None:
        from drivers.gnss import stream_framer
        return stream_framer.StreamFramer
    spec = importlib.util.spec_from_file_location("baseline_framer", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module.StreamFramer


def cost(framer_class, data: bytes, repeats: int) -> dict:
    """CPU seconds per second of input (the best of `repeats`), frames and rejections."""
    best = float("inf")
    for _ in range(repeats):
        framer = framer_class(HealthCounters("gnss"))  # as the driver runs it: every rejection counted there too
        t0 = time.process_time()
        frames = 0
        for i in range(0, len(data), READ_BYTES):
            frames += len(framer.feed(data[i:i + READ_BYTES]))
        frames += len(framer.flush())
        best = min(best, time.process_time() - t0)
    return {"bytes": len(data), "cpu_s_per_s": round(best / (len(data) / BYTES_PER_S), 5), "frames": frames,
            "rejected": sum(framer.counts.values())}


def measure(framers: dict[str, type], n: int, repeats: int) -> dict[str, dict]:
    """Each framer on each stream, the framers taking turns on a stream (a load that comes and goes hits both)."""
    streams = {"real": (real_stream(), 3 * repeats)}  # the shortest stream: more tries
    streams.update({name: (data, repeats) for name, data in hostile_streams(n, random.Random(18)).items()})
    results: dict[str, dict] = {side: {} for side in framers}
    for name, (data, tries) in streams.items():
        for side, framer_class in framers.items():
            results[side][name] = cost(framer_class, data, tries)
    for figures in results.values():
        worst = max(v["cpu_s_per_s"] for k, v in figures.items() if k != "real")
        figures["worst_over_real"] = round(worst / figures["real"]["cpu_s_per_s"], 1)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="200 kB hostile streams, best of 2 (default 1 MB, 3)")
    parser.add_argument("--baseline", type=Path, help="another stream_framer.py measured in the same run (e.g. "
                        "`git show REV:drivers/gnss/stream_framer.py > old.py`), reported as `baseline`")
    args = parser.parse_args()
    n, repeats = (200_000, 2) if args.quick else (1_000_000, 3)
    framers = {"framer": load_framer(None)}
    if args.baseline:
        framers["baseline"] = load_framer(args.baseline)
    results = measure(framers, n, repeats)
    for side, figures in results.items():
        for name, v in figures.items():
            print(f"{side} {name}: {v}", file=sys.stderr)
    results = results if args.baseline else results["framer"]
    print(json.dumps(results))


if __name__ == "__main__":
    main()
