"""Fuzzed inputs into every parser a process meets at start or on a log, counting what escapes.

- `ouster_metadata`: the shipped and the shared real Ouster metadata JSON, mutated (values of other types, sizes
  and ranges, keys deleted, text flipped, cut or nested) through what the Lidar driver checks at start
  (parse_metadata, the packet layout, the packet rate). Allowed: ValueError.
- `config`: sim.yaml and car.yaml, mutated as data (wrong types, ranges, unknown keys, ring sizes, units, signal
  names, files that are missing or junk: mutated DBCs and Lidar metadata) and as text (bytes flipped, non-UTF-8,
  tabs, anchors and alias bombs, deep nesting), through load_config and every start-up check check-config runs.
  Allowed: ConfigError.
- `mcap_reader`: closed and unclosed logs (lz4, zstd, none) damaged on disk (bit flips, zeroed 4 KiB blocks,
  random bytes, cuts, torn record headers, a power cut's torn tail), through read_log. Allowed: nothing. Also
  counted: a message returned that was not written (corrupt), messages missing from a file reported complete.
- `recovery`: the same damaged files through recover_log, the result read back. Allowed: nothing. Also counted:
  a recovered file that is not complete or does not hold exactly what read_log gave.
- `ouster_packets`: the shared real Ouster captures' datagrams (five layouts: legacy, dual, FuSa) with bytes flipped,
  cut, grown, or replaced by random datagrams of any size, through what the Lidar driver does with a batch
  (decode_packets, the scan assembler, the missing-packet count). Allowed: nothing. Also counted: a batch whose
  counts do not add up (packets in = decoded + wrong size + bad header).
- `nmea_ubx`: the shared u-blox streams (NMEA and UBX) with bytes flipped, inserted (sync bytes, false UBX headers)
  or deleted, fed in random pieces through the GNSS driver's framer and decoder. Allowed: nothing. Also counted:
  bytes neither framed nor counted as skipped, and a published fix or IMU sample with a non-finite or out-of-range
  value.
- `can`: frames of the sim DBC's wheel-speed and yaw messages, of the real Ford Fusion candump logs, and random
  ones (any id, length, error and remote flags), mutated, through the CAN driver's loop (run_can_driver on a bus
  that hands them out). Allowed: nothing. Also counted: a frame not published raw.

The sensor streams' cases and checks are in bench/sensor_stream_fuzz.py. A case that runs longer than HANG_S is a
hang (SIGALRM).

    python bench/parser_fuzz.py [--quick] [--cases N] [--seed S] [--only PARSER]

Last line: JSON {parser: {cases, uncaught, hangs, seconds, slowest_s, ...}}.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import os
import random
import signal
import sys
import tempfile
import time
import traceback
from collections import Counter
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.sensor_stream_fuzz import (  # noqa: E402
    CONFIGS,
    SHARED_OUSTER,
    CanCases,
    GnssCases,
    OusterPacketCases,
    check_can,
    check_gnss,
    check_ouster_packets,
)
from daemon.commands.check_config import start_up_problems  # noqa: E402
from daemon.log_format.reader import ReadReport, read_log  # noqa: E402
from daemon.log_format.recovery import recover_log  # noqa: E402
from daemon.log_format.writer import LogWriter  # noqa: E402
from daemon.spine.config import ConfigError, load_config  # noqa: E402
from daemon.spine.messages import CameraFrame, CanFrame, GnssFix, ImuSample, LidarPacket, TimeAnchor  # noqa: E402
from drivers.lidar.ouster_metadata import parse_metadata  # noqa: E402
from drivers.lidar.ouster_packet_layout import packet_layout, packets_per_second  # noqa: E402
from tests.log_damage import damaged_log  # noqa: E402

HANG_S = 10.0
PARSERS = ("ouster_metadata", "ouster_packets", "nmea_ubx", "can", "config", "mcap_reader", "recovery")


class Hang(BaseException):  # noqa: N818 - not an Exception: no `except Exception` in the code under test eats it
    pass


def _alarm(*_):
    raise Hang


# --- mutations ------------------------------------------------------------------------------------------------

ODD_VALUES = [None, True, False, 0, -1, 1, 7, 2**31, 2**63, -(2**70), 0.5, -1e-9, 1e308, float("inf"), float("nan"),
              "", "x", "1024x10", "rad/s", "LEGACY", "FUSA", "lidar/packets", "9" * 40, "\u00e9\u0000", [], [0],
              [1, 2], [[1, 2], [3]], ["a"] * 128, [0.0] * 16, [1e400] * 16, {}, {"a": 1}, {"": None}]


def _paths(doc, prefix=()):
    """Every (path, value) in a JSON/YAML-like tree."""
    yield prefix, doc
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:8]):  # long arrays: the first few stand for all
            yield from _paths(v, (*prefix, i))


def _set(doc, path, value):
    if not path:
        return value
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    parent[path[-1]] = value
    return doc


def _delete(doc, path):
    if path:
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        del parent[path[-1]]
    return doc


def mutate_tree(doc, rng: random.Random, extra_values=()):
    """One to three structural changes: a value replaced by an odd one, a key deleted or added, a list cut or grown,
    a number scaled."""
    doc = copy.deepcopy(doc)
    for _ in range(rng.choice((1, 1, 2, 3))):
        paths = list(_paths(doc))
        path, value = rng.choice(paths[1:] if len(paths) > 1 else paths)
        kind = rng.randrange(6)
        if kind == 0:
            doc = _set(doc, path, copy.deepcopy(rng.choice(ODD_VALUES + list(extra_values))))
        elif kind == 1 and path:
            doc = _delete(doc, path)
        elif kind == 2 and isinstance(value, dict):
            value[rng.choice(["unknown_key", "", "1", "ring_bytes"])] = copy.deepcopy(rng.choice(ODD_VALUES))
        elif kind == 3 and isinstance(value, list):
            doc = _set(doc, path, value[:rng.randrange(len(value) + 1)] if rng.random() < 0.5 else copy.deepcopy(
                value * 2))
        elif kind == 4 and isinstance(value, int | float) and not isinstance(value, bool):
            doc = _set(doc, path, value * rng.choice((-1, 0, 2, 1000, 1e-6)))
        else:
            doc = _set(doc, path, copy.deepcopy(rng.choice(ODD_VALUES)))
    return doc


def mutate_text(data: bytes, rng: random.Random, specials: list[bytes]) -> bytes:
    """One to three byte-level changes: flips, a cut, an insertion of a special token, a deleted stretch."""
    out = bytearray(data)
    for _ in range(rng.choice((1, 1, 2, 3))):
        at = rng.randrange(len(out) + 1)
        kind = rng.randrange(5)
        if kind == 0 and out:
            at = min(at, len(out) - 1)
            out[at] ^= 1 << rng.randrange(8)
        elif kind == 1:
            del out[at:]
        elif kind == 2:
            out[at:at] = rng.choice(specials)
        elif kind == 3:
            del out[at:at + rng.randrange(1, 200)]
        else:
            out[at:at] = rng.randbytes(rng.randrange(1, 16))
    return bytes(out)


JSON_SPECIALS = [b"{", b"}", b"[", b"]", b",", b":", b'"', b"null", b"-", b"1e999", b"NaN", b"[" * 5000,
                 b"\xff\xfe", b"\x00"]
YAML_SPECIALS = [b"\t", b": ", b"- ", b"&a ", b"*a", b"*b ", b"!!python/object:os.system ", b"!!binary ", b"{", b"[",
                 b"---\n", b"...\n", b"%YAML 1.1\n", b"? ", b"|\n", b">\n", b"\xe9", b"\x00", b"\r", b"9" * 5000,
                 b"[" * 3000, b"!!float 1e999", b"<<: *a\n", b"~", b".nan", b"0x", b"0o9",
                 b"a0: &a0 [x, x, x, x, x, x, x, x, x]\na1: &a1 [*a0, *a0, *a0, *a0, *a0, *a0, *a0, *a0, *a0]\n"
                 b"a2: &a2 [*a1, *a1, *a1, *a1, *a1, *a1, *a1, *a1, *a1]\na3: &a3 [*a2, *a2, *a2, *a2, *a2, *a2, *a2, "
                 b"*a2, *a2]\na4: &a4 [*a3, *a3, *a3, *a3, *a3, *a3, *a3, *a3, *a3]\na5: &a5 [*a4, *a4, *a4, *a4, *a4, "
                 b"*a4, *a4, *a4, *a4]\na6: &a6 [*a5, *a5, *a5, *a5, *a5, *a5, *a5, *a5, *a5]\n"]


# --- Ouster metadata --------------------------------------------------------------------------------------------

def metadata_bases() -> list[dict]:
    files = [CONFIGS / "sim_os128_metadata.json"] + sorted(SHARED_OUSTER.glob("*.json"))
    docs = []
    for f in files:
        try:
            parse_metadata(f)
        except ValueError:
            continue  # not sensor metadata (a digest)
        docs.append(json.loads(f.read_text()))
    return docs


def metadata_case(rng: random.Random, bases: list[dict]) -> bytes:
    doc = rng.choice(bases)
    if rng.random() < 0.7:
        return json.dumps(mutate_tree(doc, rng)).encode()
    return mutate_text(json.dumps(doc).encode(), rng, JSON_SPECIALS)


def check_metadata(data: bytes) -> str:
    """What the Lidar driver does with its metadata at start; ValueError is the parser's refusal."""
    try:
        meta = parse_metadata(data)
        layout = packet_layout(meta)
        packets_per_second(meta)
        return f"accepted {layout.profile}"
    except ValueError:
        return "refused"


# --- config -----------------------------------------------------------------------------------------------------

class ConfigCases:
    """Mutated car configs, written into `folder` with the mutated DBCs and Lidar metadata they may name."""

    def __init__(self, folder: Path, rng: random.Random):
        self.folder, self.rng = folder, rng
        sim = yaml.safe_load((CONFIGS / "sim.yaml").read_text())
        sim["sensors"]["can"]["dbc_file"] = str(CONFIGS / "sim_car.dbc")
        sim["sensors"]["lidar"]["metadata_file"] = str(CONFIGS / "sim_os128_metadata.json")
        sim["recorder"]["output_dir"] = str(folder / "logs")
        self.bases = [sim, yaml.safe_load((CONFIGS / "car.yaml").read_text())]
        self.metadata = metadata_bases()
        self.dbc = (CONFIGS / "sim_car.dbc").read_bytes()
        self.n = 0

    def _file(self, suffix: str, data: bytes) -> str:
        path = self.folder / f"f{self.n % 50}{suffix}"  # a few dozen files, reused
        path.write_bytes(data)
        return str(path)

    def __call__(self) -> Path:
        rng = self.rng
        self.n += 1
        doc = copy.deepcopy(rng.choice(self.bases))
        target = rng.random()
        if target < 0.15 and doc["sensors"].get("can"):
            doc["sensors"]["can"]["dbc_file"] = self._file(".dbc", mutate_text(self.dbc, rng, [
                b"BO_ ", b"SG_ ", b" : ", b"|", b"@0+", b"@1-", b"(", b")", b"[", b"]", b'"', b"\n", b"-", b"99999"]))
        elif target < 0.3 and doc["sensors"].get("lidar"):
            doc["sensors"]["lidar"]["metadata_file"] = self._file(".json", metadata_case(rng, self.metadata))
        elif target < 0.4:
            topic = rng.choice(["lidar/packets", "camera/front_wide", "imu", "health/recorder", "nope/topic"])
            size = rng.choice([-1, 0, 100, 4096, 100_000, 1 << 20, 1 << 40, "big", None])
            doc.setdefault("bus", {})["ring_bytes"] = {topic: size}
        elif target < 0.45 and doc["sensors"].get("can"):
            doc["sensors"]["can"]["signals"]["speed_unit"] = rng.choice(["m/s", "km/h", "rad/s", "mph", 1, None])
        extra = [str(self.folder / "missing.onnx"), str(self.folder), "../../etc/passwd", {"provider": "onnx"}]
        if rng.random() < 0.75:
            doc = mutate_tree(doc, rng, extra)
        text = yaml.safe_dump(doc, allow_unicode=True).encode() if isinstance(doc, dict) else yaml.safe_dump(
            doc).encode()
        if rng.random() < 0.35:
            text = mutate_text(text, rng, YAML_SPECIALS)
        path = self.folder / "car.yaml"
        path.write_bytes(text)
        return path


def check_config(path: Path) -> str:
    """What check-config does: load, then every start-up check; ConfigError is its refusal."""
    try:
        config = load_config(path)
    except ConfigError:
        return "refused"
    return "refused by a start-up check" if start_up_problems(config, str(path)) else "accepted"


# --- MCAP reader and recovery --------------------------------------------------------------------------------------

def _drive(n_rounds: int, rng: random.Random) -> list[tuple[str, object]]:
    out, t = [], 1_000_000_000
    for i in range(n_rounds):
        batch = [("camera/front_wide", CameraFrame(i, t, 0, "front_wide", "jpeg", 0, 0, rng.randbytes(3000))),
                 ("lidar/packets", LidarPacket(i, t + 1, 0, "lidar", rng.randbytes(rng.choice((2000, 24896))))),
                 ("gnss/fix", GnssFix(i, t + 2, 0, 48.1, 11.5, 520.0, tuple(rng.random() for _ in range(9)), 3)),
                 ("time_anchor", TimeAnchor(i, t + 3, 0, 1_763_000_000_000_000_000 + i))]
        batch += [("imu", ImuSample(5 * i + k, t + 4 + k, 0, (0.1 * k, 0.0, 9.81), (0.0, 0.0, 0.01))) for k in range(5)]
        batch += [("can/frames", CanFrame(8 * i + k, t + 10 + k, 0, 0x200 + k, False, False, False, "can0",
                                          bytes([i % 256, k] * 4))) for k in range(8)]
        for k, (_, msg) in enumerate(batch):
            msg.host_mono_ns = t + 100 + k
        out += batch
        t += 100_000_000
    return out


class LogCases:
    """Closed and unclosed logs (three compressions), damaged."""

    def __init__(self, folder: Path, rng: random.Random):
        self.folder, self.rng = folder, rng
        config = load_config(CONFIGS / "sim.yaml")
        self.config = config
        self.bases = []
        for compression in ("lz4", "zstd", "none"):
            msgs = _drive(25, random.Random(compression))
            closed = folder / f"base_{compression}.mcap"
            writer = LogWriter(closed, config, compression=compression, chunk_size=32 * 1024)
            for topic, msg in msgs:
                writer.write(topic, msg)
            writer.flush()
            unclosed = closed.read_bytes()
            writer.close()
            originals = {(t, m.host_mono_ns): m for t, m in msgs}
            self.bases += [(closed.read_bytes(), originals), (unclosed, originals)]
        self.path = folder / "damaged.mcap"

    def __call__(self) -> tuple[Path, dict]:
        data, originals = self.rng.choice(self.bases)
        self.path.write_bytes(damaged_log(data, self.rng))
        return self.path, originals


def check_reader(case, counts: Counter) -> str:
    path, originals = case
    report = ReadReport()
    got = {(r.topic, r.log_time_ns): r.message for r in read_log([path], report=report)}
    if any(k not in originals or originals[k] != m for k, m in got.items()):
        counts["corrupt_returned"] += 1
    if len(got) < len(originals) and report.files[0].complete:
        counts["hidden_losses"] += 1
    return "complete" if report.files[0].complete else "damage reported"


def check_recovery(case, counts: Counter, config, folder: Path) -> str:
    path, _ = case
    fixed = folder / "fixed.mcap"
    kept = recover_log(path, fixed, config)
    report = ReadReport()
    again = [(r.topic, r.log_time_ns) for r in read_log([fixed], report=report)]
    if not report.files[0].complete or len(again) != kept.messages:
        counts["recovered_not_whole"] += 1
    return "recovered in full" if kept.complete else "recovered with damage skipped"


# --- sensor streams: Ouster packets, NMEA/UBX, CAN -----------------------------------------------------------------


def fuzz(name: str, make_case, check, n: int, tallies: tuple[str, ...] = (), examples: int = 5) -> dict:
    """Run `n` cases of one parser; the tally (with the parser's own `tallies`, 0 when nothing was found)."""
    counts: Counter = Counter({k: 0 for k in tallies})
    outcomes: Counter = Counter()
    found: list[str] = []
    slowest = 0.0
    started = time.perf_counter()
    previous = signal.signal(signal.SIGALRM, _alarm)
    try:
        for i in range(n):
            case = make_case()
            t0 = time.perf_counter()
            signal.setitimer(signal.ITIMER_REAL, HANG_S)
            try:
                outcomes[check(case, counts)] += 1
            except Hang:
                counts["hangs"] += 1
                found.append(f"case {i}: hang (> {HANG_S} s)")
            except Exception as exc:  # noqa: BLE001 - this is what the bench counts
                counts["uncaught"] += 1
                if len(found) < examples:
                    where = traceback.extract_tb(exc.__traceback__)[-1]
                    found.append(f"case {i}: {type(exc).__name__}: {str(exc)[:120]} "
                                 f"({Path(where.filename).name}:{where.lineno})")
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            slowest = max(slowest, time.perf_counter() - t0)
    finally:
        signal.signal(signal.SIGALRM, previous)
    result = {"cases": n, "uncaught": counts.pop("uncaught", 0), "hangs": counts.pop("hangs", 0),
              "seconds": round(time.perf_counter() - started, 1), "slowest_s": round(slowest, 3),
              **dict(counts), "outcomes": dict(outcomes)}
    if found:
        result["examples"] = found
    print(f"{name}: {json.dumps(result)}", file=sys.stderr, flush=True)
    return result


def run(parsers: list[str], cases: int, seed: int) -> dict:
    os.environ.pop("ROADLOG_SIMULATED_SHM_BYTES", None)
    results = {}
    with tempfile.TemporaryDirectory(prefix="roadlog-fuzz-") as tmp:
        folder = Path(tmp)
        if "ouster_metadata" in parsers:
            rng = random.Random(seed)
            bases = metadata_bases()
            results["ouster_metadata"] = fuzz("ouster_metadata", lambda: metadata_case(rng, bases),
                                              lambda data, _: check_metadata(data), cases)
        if "ouster_packets" in parsers:
            results["ouster_packets"] = fuzz("ouster_packets", OusterPacketCases(random.Random(seed + 3)),
                                             check_ouster_packets, cases, ("counts_inconsistent",))
        if "nmea_ubx" in parsers:
            results["nmea_ubx"] = fuzz("nmea_ubx", GnssCases(random.Random(seed + 4)), check_gnss, cases,
                                       ("bytes_unaccounted", "bad_published"))
        if "can" in parsers:
            make = CanCases(random.Random(seed + 5))
            results["can"] = fuzz("can", make, lambda case, counts: check_can(case, counts, make.config, make.dbc),
                                  cases, ("frames_not_published",))
        if "config" in parsers:
            (folder / "config").mkdir()
            make = ConfigCases(folder / "config", random.Random(seed + 1))
            results["config"] = fuzz("config", make, lambda path, _: check_config(path), cases)
        if {"mcap_reader", "recovery"} & set(parsers):
            (folder / "logs").mkdir()
            logs = LogCases(folder / "logs", random.Random(seed + 2))
            if "mcap_reader" in parsers:
                results["mcap_reader"] = fuzz("mcap_reader", logs, check_reader, cases,
                                              ("corrupt_returned", "hidden_losses"))
            if "recovery" in parsers:
                results["recovery"] = fuzz("recovery", logs, lambda case, counts: check_recovery(
                    case, counts, logs.config, folder / "logs"), cases, ("recovered_not_whole",))
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="300 cases per parser instead of 3,000")
    parser.add_argument("--cases", type=int, help="cases per parser")
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--only", choices=PARSERS, action="append", help="this parser only (repeatable)")
    args = parser.parse_args()
    logging.getLogger("daemon").setLevel(logging.CRITICAL)  # the reader's line per damaged file, thousands of them
    cases = args.cases or (300 if args.quick else 3000)
    results = run(args.only or list(PARSERS), cases, args.seed)
    results["total"] = {"cases": sum(r["cases"] for r in results.values()),
                        "uncaught": sum(r["uncaught"] for r in results.values()),
                        "hangs": sum(r["hangs"] for r in results.values())}
    print(json.dumps(results))


if __name__ == "__main__":
    main()
