"""The soak: the whole daemon (`roadlog run`: supervisor, drivers, recorder, mapper, status server) on a simulated
drive played again and again over the real protocols (Ouster UDP, NMEA + UBX on a pseudo-terminal, CAN on
udp_multicast, sim cameras looping the same log) for `--duration` seconds, then stopped with SIGTERM.

    python bench/soak.py [--quick] [--duration S] [--drive LOG] [--work DIR]

Every `--sample-s` it samples the RSS of every process of the daemon (by its name in the supervisor's table, with
its children), the load average, the free disk and the mapper's windows; it counts every closed segment from its
summary (messages per topic, and the recorder's own `lost_per_topic`) and deletes it, so an hour's recording (~22
MB/s) does not fill the disk. The drive ends at the end of a pass, so what was sent is exact: the simulator's own
counts (Lidar packets and IMU, CAN, GNSS fixes and IMU samples; wheel speeds are passes x the drive's), and each
camera's own `published` from its last logged health. What is missing is accounted for by the recorder's lost count,
the Lidar driver's own count of packets missing from the sensor's numbering (lost in the socket before it read them),
and the simulator's count of fixes and IMU samples cut off by a full pseudo-terminal (a serial overrun: the GNSS
driver did not read in time): `unaccounted` is what none of them counted. Last line: one JSON object (per-topic
sent/logged/lost, RSS per process start/end/max and slope, mapper windows, stop exit code and seconds, orphans, load
average). The mapper's part (`mapper`): its windows by outcome from its journal (done, failed, skipped behind the
car, skipped at the stop: mapping.live.lag_policy), how far behind it was at the stop, what it held in memory at
the start and the end of the drive (counts from its health), its own stop time from its log and whether the
supervisor killed any process at its stop timeout. `--mapper-slow-s S` makes each window take at least S s
(`mapper.lag.min_window_wall_s`): a mapper that cannot keep up, on any machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path

import numpy as np
import psutil
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.bus.pubsub import unlink_all  # noqa: E402
from daemon.log_format.reader import read_log, read_metadata, summary_message_counts  # noqa: E402
from daemon.processes import child_launch  # noqa: E402
from daemon.spine.config import load_config  # noqa: E402
from daemon.spine.topics import health_topic  # noqa: E402
from drivers.can.can_bus import open_can_bus  # noqa: E402
from drivers.lidar.ouster_metadata import parse_metadata  # noqa: E402
from drivers.lidar.ouster_packet_layout import packet_layout  # noqa: E402
from mapping.live.worker_journal import read_journal  # noqa: E402
from sim.live_drive import LiveDriveStats, open_gnss_pty, run_live_drive  # noqa: E402
from tests.daemon_fixtures import free_port, http_json  # noqa: E402

# the simulator's own counts of what it sent, per topic
SIMULATOR_SENT = {"lidar/packets": "lidar_packets", "lidar/imu": "lidar_imu_packets", "can/frames": "can_frames",
                  "gnss/fix": "gnss_fixes", "imu": "imu_samples"}
MIN_FREE_DISK_GB = 15.0  # the soak stops its drive early rather than fill a disk other people use
STOP_TIMEOUT_S = 900.0


def write_config(work: Path, drive: Path, pty_path: str, segment_s: float, mapper: bool,
                 mapper_slow_s: float = 0.0) -> Path:
    """configs/sim.yaml with private ports and bus prefix, looping sim cameras, logs under work/data."""
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"] = {"shm_prefix": f"soak{uuid.uuid4().hex[:8]}"}
    s = data["sensors"]
    for cam in s["cameras"]:
        cam.update(device=str(drive), loop=True)
    s["lidar"].update(port=free_port(socket.SOCK_DGRAM), imu_port=free_port(socket.SOCK_DGRAM),
                      metadata_file=str(ROOT / "configs" / s["lidar"]["metadata_file"]))
    s["gnss"]["port"] = pty_path
    s["can"].update(dbc_file=str(ROOT / "configs" / s["can"]["dbc_file"]),
                    options={"port": random.randint(40000, 49000)})
    data["recorder"].update(output_dir=str(work / "data"), segment_seconds=segment_s)
    data["mapper"]["enabled"] = mapper
    if mapper_slow_s:
        data["mapper"]["lag"] = {"min_window_wall_s": mapper_slow_s}
    data["status"]["port"] = free_port()
    path = work / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class SegmentTally:
    """Counts each closed segment from its summary (and the recorder's lost counts), then deletes it."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.logged: Counter = Counter()
        self.lost: Counter = Counter()
        self.segments = 0
        self.unreadable: list[str] = []
        self.last_kept: list[Path] = []

    def take(self, keep_last: bool) -> None:
        closed = sorted(self.folder.glob("*.mcap"))
        if keep_last:  # the newest closed segment stays for the cameras' last health
            closed = closed[:-1]
        for seg in closed:
            self.count(seg)
            seg.unlink()

    def count(self, seg: Path) -> None:
        counts = summary_message_counts(seg)
        if counts is None:
            self.unreadable.append(seg.name)
            return
        self.logged.update(counts)
        lost = read_metadata(seg).get("roadlog.counts", {}).get("lost_per_topic", "{}")
        self.lost.update(json.loads(lost))
        self.segments += 1


def _runqueue_wait_s(pid: int) -> float:
    """How long the process's threads have waited, runnable, for a CPU (the scheduler's own count)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            total += int((task / "schedstat").read_text().split()[1])
        except (OSError, IndexError, ValueError):
            continue
    return total / 1e9


class ProcessSampler:
    """RSS (MB, with children) of every named process of the daemon over time, and its CPU time and time waiting
    for a CPU (its own threads; where a process loses data, this tells a starved process from a slow one)."""

    def __init__(self, supervisor_pid: int):
        self.supervisor_pid = supervisor_pid
        self.samples: dict[str, list[tuple[float, float]]] = {}
        self.cpu: dict[str, list[tuple[float, float, float]]] = {}  # name -> (t, cpu s, runqueue wait s)
        self.pids: dict[str, set[int]] = {}
        self.seen: dict[int, float] = {}  # every pid of the daemon's tree -> its create time

    def sample(self, status: dict, t: float) -> None:
        procs = {"supervisor": self.supervisor_pid}
        for name, info in status.get("supervisor", {}).get("processes", {}).items():
            if info.get("pid"):
                procs[name] = info["pid"]
        for name, pid in procs.items():
            try:
                p = psutil.Process(pid)
                tree = [p] if name == "supervisor" else [p, *p.children(recursive=True)]
                rss = sum(q.memory_info().rss for q in tree) / 1e6
                times = p.cpu_times()
                cpu = (t, times.user + times.system, _runqueue_wait_s(pid))
                for q in [p, *p.children(recursive=True)]:
                    self.seen.setdefault(q.pid, q.create_time())
            except psutil.Error:
                continue
            self.samples.setdefault(name, []).append((t, rss))
            self.cpu.setdefault(name, []).append(cpu)
            self.pids.setdefault(name, set()).add(pid)

    def orphans(self) -> list[str]:
        left = []
        for pid, created in self.seen.items():
            try:
                p = psutil.Process(pid)
                if p.create_time() == created and p.status() != psutil.STATUS_ZOMBIE:
                    left.append(f"{pid} {' '.join(p.cmdline()[:4])}")
            except psutil.Error:
                continue
        return left

    def report(self, warmup_s: float) -> dict:
        out = {}
        for name, series in sorted(self.samples.items()):
            t = np.array([s[0] for s in series])
            rss = np.array([s[1] for s in series])
            late = t >= min(warmup_s, t[-1] / 2)
            slope = float(np.polyfit(t[late] / 3600, rss[late], 1)[0]) if late.sum() >= 3 else None
            out[name] = {"start_mb": round(float(rss[0]), 1), "end_mb": round(float(rss[-1]), 1),
                         "max_mb": round(float(rss.max()), 1),
                         "after_warmup_start_mb": round(float(rss[late][0]), 1),
                         "slope_mb_per_h": None if slope is None else round(slope, 1),
                         "samples": len(series), "pids": len(self.pids[name])}
            (t0, cpu0, wait0), (t1, cpu1, wait1) = self.cpu[name][0], self.cpu[name][-1]
            if t1 > t0 and len(self.pids[name]) == 1:
                out[name]["cpu_pct"] = round(100 * (cpu1 - cpu0) / (t1 - t0), 1)
                out[name]["runqueue_wait_pct"] = round(100 * (wait1 - wait0) / (t1 - t0), 1)
        return out


def simulate(work: Path, scenario: str, seconds: float, seed: int) -> Path:
    drive = work / f"{scenario}-{seconds:g}s-seed{seed}.mcap"
    if not drive.exists():
        subprocess.run([sys.executable, "-m", "daemon.commands.cli", "simulate", "--scenario", scenario,
                        "--seconds", str(seconds), "--seed", str(seed), "--out", str(drive)], cwd=ROOT, check=True,
                       stdout=subprocess.DEVNULL)
    return drive


def mapper_report(folder: Path, daemon_log: Path, held: list[dict], before_stop: dict) -> dict:
    """The mapper's windows by outcome (its journal), its lag at the stop, what it held in memory at the drive's start
    and end, its own stop time (its log) and the processes the supervisor killed at their stop timeout."""
    journal = read_journal(folder)
    outcomes: Counter = Counter()
    for w in journal.windows if journal is not None else []:
        outcomes[w.status if w.status != "skipped" else f"skipped_{(w.reason or '').split(':')[0]}"] += 1
    text = daemon_log.read_text(errors="replace") if daemon_log.exists() else ""
    stop_s = re.findall(r"final map in .*?, ([0-9.]+) s after the stop request", text)
    return {"windows": dict(outcomes), "finished": bool(journal and journal.finished),
            "lag_m_at_stop": before_stop.get("lag_m"), "distance_m_at_stop": before_stop.get("distance_m"),
            "skipped_m": before_stop.get("skipped_m"), "held_start": held[0] if held else None,
            "held_end": held[-1] if held else None, "stop_s": float(stop_s[-1]) if stop_s else None,
            "killed_at_stop_timeout": re.findall(r"(\w+) did not stop within its stop timeout", text)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=3600.0, help="seconds of driving (whole passes)")
    parser.add_argument("--quick", action="store_true", help="a 40 s drive (under a minute of driving)")
    parser.add_argument("--drive", type=Path, help="a drive made by `roadlog simulate` (default: simulated here)")
    parser.add_argument("--drive-seconds", type=float, default=8.0)
    parser.add_argument("--scenario", default="city")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--work", type=Path, help="working folder (default: a new one under /tmp)")
    parser.add_argument("--sample-s", type=float, default=10.0)
    parser.add_argument("--segment-s", type=float, default=60.0)
    parser.add_argument("--no-mapper", action="store_true")
    parser.add_argument("--mapper-slow-s", type=float, default=0.0,
                        help="each mapper window takes at least this long (s): a mapper that falls behind")
    args = parser.parse_args(argv)
    if args.quick:
        args.duration, args.sample_s, args.segment_s = 40.0, 2.0, 10.0
    work = args.work or Path(tempfile.mkdtemp(prefix="roadlog-soak-"))
    work.mkdir(parents=True, exist_ok=True)
    drive = args.drive or simulate(work, args.scenario, args.drive_seconds, args.seed)
    drive_counts = summary_message_counts(drive)
    period_s = float(read_metadata(drive)["roadlog"]["seconds"])
    passes = max(1, math.ceil(args.duration / period_s))
    if (work / "data").exists():
        shutil.rmtree(work / "data")

    pty = open_gnss_pty()
    config_path = write_config(work, drive, pty.path, args.segment_s, not args.no_mapper, args.mapper_slow_s)
    config = load_config(config_path)
    port = config.status.port
    layout = packet_layout(parse_metadata(Path(config.sensors.lidar.metadata_file)))
    daemon_log = open(work / "daemon.log", "wb")
    started = time.monotonic()
    # the daemon is stopped (SIGTERM) however this process ends: killed (the kernel's death signal) or told to stop
    daemon = subprocess.Popen(child_launch.command("daemon.commands.cli", ["run", "--config", str(config_path)],
                                                   sig=signal.SIGTERM),
                              cwd=ROOT, start_new_session=True, stdout=daemon_log, stderr=subprocess.STDOUT)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, lambda signum, _: sys.exit(128 + signum))  # the `finally` below stops the daemon
    sampler = ProcessSampler(daemon.pid)
    tally = SegmentTally(work / "data")
    result: dict = {"work": str(work), "duration_s": args.duration, "passes_planned": passes,
                    "drive_s": period_s, "mapper": not args.no_mapper}
    loads: list[float] = []
    losses: list[tuple[float, int]] = []  # (drive s, the recorder's lost count) where it changed
    free_gb: list[float] = []
    stop_drive = threading.Event()
    final_health: dict = {}
    mapper_held: list[dict] = []  # what the mapper held in memory (its health's counts), first and latest
    stats_box: list[LiveDriveStats] = []
    try:
        names = {"lidar", "gnss", "can", "recorder", *(f"camera_{c.name}" for c in config.sensors.cameras)}
        deadline = time.monotonic() + 180
        while not names <= set(http_json(port, "/status", timeout_s=5.0)[1].get("processes", {})):
            if time.monotonic() > deadline or daemon.poll() is not None:
                raise RuntimeError(f"the daemon did not come up (see {work / 'daemon.log'})")
            time.sleep(0.5)
        result["startup_s"] = round(time.monotonic() - started, 1)

        bus = open_can_bus(config.sensors.can)

        def play() -> None:
            try:
                stats_box.append(run_live_drive(
                    drive, lidar_address=("127.0.0.1", config.sensors.lidar.port), gnss_fd=pty.master_fd,
                    can_bus=bus, stop=stop_drive, passes=passes, lidar_layout=layout,
                    lidar_imu_address=("127.0.0.1", config.sensors.lidar.imu_port)))
            finally:
                bus.shutdown()

        player = threading.Thread(target=play, name="live-drive")
        t0 = time.monotonic()
        player.start()
        status: dict = {}
        while player.is_alive():
            player.join(args.sample_s)
            status = http_json(port, "/status", timeout_s=5.0)[1]
            sampler.sample(status, time.monotonic() - t0)
            if "held" in status.get("mapping", {}):
                mapper_held[1:] = [status["mapping"]["held"] | {"rss_mb": status["mapping"].get("rss_mb")}]
            lost_now = sum(status.get("recorder", {}).get("lost", {}).values())
            if lost_now != (losses[-1][1] if losses else 0):
                losses.append((round(time.monotonic() - t0, 1), lost_now))
            loads.append(os.getloadavg()[0])
            free_gb.append(shutil.disk_usage(work).free / 1e9)
            tally.take(keep_last=True)
            if free_gb[-1] < MIN_FREE_DISK_GB and not stop_drive.is_set():
                result["stopped_early"] = f"free disk {free_gb[-1]:.1f} GB < {MIN_FREE_DISK_GB} GB"
                stop_drive.set()
            if daemon.poll() is not None:
                result["stopped_early"] = f"the daemon exited with {daemon.returncode} during the drive"
                stop_drive.set()
        result["drive_wall_s"] = round(time.monotonic() - t0, 1)
        time.sleep(3.0)  # the cameras' and the recorder's last messages
        status = http_json(port, "/status", timeout_s=5.0)[1]
        sampler.sample(status, time.monotonic() - t0)
        result["mapping_before_stop"] = status.get("mapping", {})
        final_health = status.get("processes", {})
        result["restarts"] = {n: p.get("restarts", 0)
                              for n, p in status.get("supervisor", {}).get("processes", {}).items()}
        t_stop = time.monotonic()
        daemon.send_signal(signal.SIGTERM)
        try:
            result["stop_exit_code"] = daemon.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            result["stop_exit_code"] = None
        result["stop_s"] = round(time.monotonic() - t_stop, 1)
    finally:
        stop_drive.set()
        if daemon.poll() is None:  # stopped early (an error, a signal): stopped as asked, then killed
            daemon.send_signal(signal.SIGTERM)
            try:
                daemon.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(daemon.pid, signal.SIGKILL)
                daemon.wait()
        daemon_log.close()
        pty.close()
        result["orphans"] = sampler.orphans()
        unlink_all(config)

    stats = stats_box[0] if stats_box else LiveDriveStats()
    data = work / "data"
    result["segments_open_after_stop"] = sorted(p.name for p in data.glob("*.open"))
    last = sorted(data.glob("*.mcap"))
    cameras = {c.name: {"published": 0, "dropped": 0} for c in config.sensors.cameras}
    for rec in read_log(last, topics=[health_topic(f"camera_{c}") for c in cameras]):
        cameras[rec.message.process.removeprefix("camera_")] = {"published": rec.message.published,
                                                                "dropped": rec.message.dropped}
    for seg in last:
        tally.count(seg)
    topics = {}
    for topic, field_name in SIMULATOR_SENT.items():
        topics[topic] = {"sent": getattr(stats, field_name)}
    topics["wheel_speeds"] = {"sent": stats.passes * drive_counts.get("wheel_speeds", 0)
                              if stats.passes == passes else None}
    for cam, health in cameras.items():
        topics[f"camera/{cam}+mask/{cam}"] = {"sent": health["published"], "camera_dropped": health["dropped"]}
    # lost before the driver: Lidar packets missing from the sensor's numbering when the driver read its socket (the
    # driver's count), fixes and IMU samples whose bytes did not fit into the full pseudo-terminal (the simulator's)
    topics["lidar/packets"]["lost_before_driver"] = final_health.get("lidar", {}).get("dropped")
    topics["gnss/fix"]["lost_before_driver"] = stats.gnss_fixes_cut
    topics["imu"]["lost_before_driver"] = stats.imu_samples_cut
    for topic, row in topics.items():
        parts = topic.split("+")
        row["logged"] = sum(tally.logged[p] for p in parts)
        row["lost_recorder"] = sum(tally.lost[p] for p in parts)
        row["missing"] = None if row["sent"] is None else row["sent"] - row["logged"]
        row["unaccounted"] = None if row["sent"] is None else (row["missing"] - row["lost_recorder"]
                                                               - (row.get("lost_before_driver") or 0))
    result.update({
        "passes_done": stats.passes, "simulator": {"late": stats.late, "errors": stats.errors,
                                                   "gnss_dropped_bytes": stats.gnss_dropped_bytes,
                                                   "last_error": stats.last_error},
        "topics": topics, "lost_recorder_all": dict(tally.lost), "segments": tally.segments,
        "segments_unreadable": tally.unreadable,
        "rss": sampler.report(warmup_s=min(300.0, args.duration / 5)),
        "load_avg_1m": {"start": round(loads[0], 2) if loads else None, "end": round(loads[-1], 2) if loads else None,
                        "max": round(max(loads), 2) if loads else None,
                        "mean": round(float(np.mean(loads)), 2) if loads else None},
        "recorder_lost_over_time": losses,
        "free_disk_gb_min": round(min(free_gb), 1) if free_gb else None,
        "map_final": (data / "map" / "final" / "metadata.json").exists(),
        "mapper": mapper_report(data / "map", work / "daemon.log", mapper_held, result.get("mapping_before_stop", {}))
        if not args.no_mapper else None,
    })
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
