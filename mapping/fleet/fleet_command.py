"""`roadlog fleet reconstruct LOG... --out DIR [--address ray://...]`: many drives mapped on Ray into one tile store
and one merged map.

Each LOG is one drive (the segments of one drive joined by commas). One Ray task per drive reads its logs once and
fits its 160 m windows one after another (docs/fleet.md: reading a drive costs as much as fitting a window, so a
task per window would read it once per window); every window's result goes into the tile store
(mapping.fleet.tile_store) and the journal (mapping.fleet.fleet_journal) as soon as it is done. A window marked
done is never fitted again: a second run with the same DIR only fits what failed or never ran. A window that
raises is tried again up to --retries times in its task, then reported failed; the other windows and drives go
on. A task whose worker dies is rerun by Ray (its done windows skipped). When every task has ended the drives are
merged (mapping.fleet.drive_merge) into DIR/map.

stderr gets a progress line for the whole job whenever a window ends; stdout one JSON summary. Exit status 0 when
every window is done, 1 when some failed (the map is made of the others), 2 for a configuration error.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

from daemon.log_format.reader import not_a_log
from daemon.spine.config import ConfigError, reports_config_errors
from mapping.fleet.drive_windows import cut_window, drive_id, fit_window, window_count
from mapping.fleet.fleet_journal import FleetJournal
from mapping.fleet.geodetic_grid import GridSpec
from mapping.fleet.tile_store import TileStore

TASK_RETRIES = 2  # Ray reruns a task whose worker died this many times


def with_mapper(config, mapper: dict | None):
    """The car's recorded config with the job's `mapper:` section in its place (None: the recorded one)."""
    from daemon.spine.mapper_config import MapperConfig

    return config if mapper is None else config.model_copy(update={"mapper": MapperConfig.model_validate(mapper)})


def mapper_section(path: Path) -> dict:
    """The `mapper:` section of a YAML file (a car config or the section alone), validated; a ConfigError if bad."""
    from pydantic import ValidationError

    from daemon.spine.mapper_config import MapperConfig
    from daemon.spine.yaml_document import UnusableYaml, load_yaml

    try:
        data = load_yaml(path.read_bytes())
    except (OSError, UnusableYaml) as exc:
        raise ConfigError(f"--mapper {path}: {exc}") from None
    section = data.get("mapper", data) if isinstance(data, dict) else data
    try:
        return MapperConfig.model_validate(section).model_dump(mode="json")
    except ValidationError as exc:
        raise ConfigError(f"--mapper {path}: " + "; ".join(
            f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())) from None


def map_drive(logs: list[str], out: str, retries: int, device: str | None, mapper: dict | None = None) -> dict:
    """One drive's windows into the tile store; what happened (the task's result). Runs in a Ray worker."""
    from mapping.inputs.drive_inputs import start_loading_drive
    from mapping.method.compute_device import with_device
    from mapping.offline.reconstruct_command import config_from_logs

    started = time.perf_counter()
    root = Path(out)
    journal, store = FleetJournal(root), TileStore(root)
    name = drive_id(logs)
    summary = {"drive": name, "logs": logs, "windows": 0, "fitted": 0, "reused": 0, "failed": [], "load_s": None}
    known = journal.drive(name)
    if known is not None and all(journal.done(name, k) for k in range(known["windows"])):
        return summary | {"windows": known["windows"], "reused": known["windows"], "wall_s": 0.0}
    try:
        config, config_path = config_from_logs(logs)
        config = with_device(with_mapper(config, mapper), device)
        drive = start_loading_drive(logs, config, config_path).result()
    except Exception as exc:  # an unreadable drive is this drive's failure, not the job's
        return summary | {"error": f"{type(exc).__name__}: {exc}", "wall_s": time.perf_counter() - started}
    load_s = time.perf_counter() - started
    windows = window_count(drive.path, config)
    frame = drive.trajectory.local_frame
    journal.write_drive(name, {"logs": logs, "windows": windows, "load_s": load_s, "drive_s": drive.drive_s,
                               "origin_lat_lon_alt": [frame.lat_deg, frame.lon_deg, frame.alt_m],
                               "cameras": sorted(drive.cameras), "inputs": drive.counts,
                               "gnss_std_m": drive.gnss_std_m})
    grid = GridSpec(config.mapper.mesh.side_m)
    stem = Path(logs[0]).stem
    summary.update(windows=windows, load_s=load_s, window_s=[])
    for k in range(windows):
        if journal.done(name, k):
            summary["reused"] += 1
            continue
        errors = []
        for attempt in range(1, retries + 2):
            t0 = time.perf_counter()
            try:
                entry = fit_window(drive, cut_window(drive, k, config), config, name, stem, store, grid)
            except Exception as exc:  # counted, journalled, tried again; never the end of the job
                errors.append(f"attempt {attempt}: {type(exc).__name__}: {exc}")
                tail = traceback.format_exc(limit=3).strip().splitlines()[-1]
                print(f"roadlog fleet: drive {name} window {k}: {tail}", file=sys.stderr, flush=True)
                continue
            wall = time.perf_counter() - t0
            journal.write_window(name, k, {"status": "done", "attempts": attempt, "wall_s": wall,
                                           "errors": errors, **entry})
            summary["fitted"] += 1
            summary["window_s"].append(wall)
            break
        else:
            journal.write_window(name, k, {"status": "failed", "attempts": retries + 1, "errors": errors})
            summary["failed"].append({"window": k, "errors": errors})
    return summary | {"wall_s": time.perf_counter() - started}


def run_job(drives: list[list[str]], out: Path, address: str | None, workers: int, retries: int,
            device: str | None, mapper: dict | None = None) -> dict:
    """Every drive as one Ray task on the cluster at `address` (None: a new local Ray of `workers` CPUs)."""
    try:
        import ray  # the fleet's optional dependency (pip install roadlog[fleet]): only this command imports it
    except ImportError:
        raise ConfigError("roadlog fleet needs Ray, its optional dependency: pip install -e '.[fleet]' "
                          "(ray 2.60.0)") from None

    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    journal = FleetJournal(out)
    if address:
        ray.init(address=address, logging_level="WARNING", log_to_driver=False)
    else:  # always a Ray of its own, never another user's cluster on this machine
        ray.init(address="local", num_cpus=workers, include_dashboard=False, logging_level="WARNING",
                 log_to_driver=False)
    ray_s = time.perf_counter() - started
    tasks_started = tasks_ended = time.perf_counter()  # the tasks' wall time: Ray's start and shutdown left out
    try:
        task = ray.remote(num_cpus=1, max_retries=TASK_RETRIES)(map_drive)
        pending = [task.remote(logs, str(out.resolve()), retries, device, mapper) for logs in drives]
        results, last = [], None
        while pending:
            ready, pending = ray.wait(pending, timeout=1.0)
            for ref in ready:
                try:
                    results.append(ray.get(ref))
                except Exception as exc:  # its worker died TASK_RETRIES + 1 times
                    results.append({"drive": None, "error": f"{type(exc).__name__}: {exc}", "failed": []})
            state = journal.progress()
            if state != last:
                done, failed, known = state
                print(f"roadlog fleet: [{time.perf_counter() - started:6.1f} s] windows done {done}, failed {failed}, "
                      f"of {known} in the {sum(journal.drive(r) is not None for r in _drive_ids(out))} drives read "
                      f"({len(drives)} given, {len(drives) - len(pending)} finished)", file=sys.stderr, flush=True)
                last = state
        tasks_ended = time.perf_counter()
    finally:
        ray.shutdown()
    return {"drives": results, "ray_start_s": ray_s, "tasks_wall_s": tasks_ended - tasks_started}


def _drive_ids(out: Path) -> list[str]:
    return [p.name for p in sorted((out / "journal").glob("*"))]


def reconstruct_main(argv: list[str]) -> int:
    from mapping.method.compute_device import DEVICES

    parser = argparse.ArgumentParser(prog="roadlog fleet reconstruct", description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", help="one drive's log (its segments joined by commas), per drive")
    parser.add_argument("--out", required=True, type=Path, help="the job's folder: tiles, journal, merged map")
    parser.add_argument("--address", help="a Ray cluster (ray://HOST:PORT); default: a local Ray on this machine")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="CPUs of the local Ray (one drive each at a time; default: this machine's)")
    parser.add_argument("--retries", type=int, default=2, help="further attempts at a window that failed")
    parser.add_argument("--device", choices=DEVICES, help="torch device of the fits (default: the logs' config)")
    parser.add_argument("--mapper", type=Path,
                        help="a YAML `mapper:` section for every drive in place of its recorded one (resolution, "
                             "windows, fits)")
    parser.add_argument("--no-merge", action="store_true", help="fill the tile store only")
    args = parser.parse_args(argv)
    drives = [item.split(",") for item in args.logs]
    problems = [why for logs in drives for why in map(not_a_log, logs) if why]
    for flag, ok in (("--workers", args.workers >= 1), ("--retries", args.retries >= 0)):
        if not ok:
            problems.append(f"{flag} must be >= {0 if flag == '--retries' else 1}")
    if args.out.exists() and not args.out.is_dir():
        problems.append(f"--out {args.out}: a file, not a folder")
    if problems:
        raise ConfigError("; ".join(problems))
    mapper = mapper_section(args.mapper) if args.mapper else None
    started = time.perf_counter()
    job = run_job(drives, args.out, args.address, args.workers, args.retries, args.device, mapper)
    done, failed, known = FleetJournal(args.out).progress()
    summary = {"windows_done": done, "windows_failed": failed, "windows": known,
               "windows_fitted": sum(r.get("fitted", 0) for r in job["drives"]),
               "windows_reused": sum(r.get("reused", 0) for r in job["drives"]),
               "drives_failed": [r for r in job["drives"] if r.get("error")],
               "failures": [{"drive": r["drive"], **f} for r in job["drives"] for f in r.get("failed", [])],
               "ray_start_s": job["ray_start_s"], "tasks_wall_s": job["tasks_wall_s"], "drives": job["drives"]}
    if not args.no_merge and TileStore(args.out).tiles():
        from mapping.fleet.drive_merge import merge_drives

        t0 = time.perf_counter()
        summary["merge"] = merge_drives(TileStore(args.out), args.out / "map")
        summary["merge_wall_s"] = time.perf_counter() - t0
    summary["wall_s"] = time.perf_counter() - started
    (args.out / "fleet.json").write_text(json.dumps(summary, indent=1, default=str))
    print(json.dumps({k: v for k, v in summary.items() if k != "drives"}, default=str))
    return 0 if not summary["failures"] and not summary["drives_failed"] else 1


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print("usage: roadlog fleet reconstruct LOG... --out DIR [--address ray://HOST:PORT] (reconstruct --help)")
        return 0
    if not argv or argv[0] != "reconstruct":
        raise ConfigError("usage: roadlog fleet reconstruct LOG... --out DIR [--address ray://HOST:PORT]")
    return reconstruct_main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
