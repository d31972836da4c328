"""Peak memory of the mapping worker for a short and a long drive: does it stay flat with the drive's length?

Simulating a long drive with cameras is far too slow on this machine, so the worker (the real process,
through the real shared-memory bus, optimising real windows) is fed a synthetic drive: a car going
anticlockwise round a 2 km-radius circle at 20 m/s (a 10 km drive never comes back over its own
road, so anything that grows with the map's extent shows), with consistent GNSS fixes (10 Hz), IMU
samples (100 Hz) and wheel speeds (50 Hz), and the front_left camera's frames and masks of a 2 s
simulated city drive (one camera, no Lidar; simulated while the workers start) replayed cyclically at
10 Hz, restamped onto the synthetic clock. The images do not match the poses (the map is meaningless)
but every window is optimised on real keyframes. The feed stays at most `--lead-m` (two windows)
ahead of the worker's mapped distance, as with a worker that keeps up with the car.

Cheap windows, the same for both drives and both modes, so that many fit in the time: 160 m windows
(the default length), a 0.8 m mesh, 4 m corridor half-width, 6 m keyframe spacing, one torch thread (the
fast fit's default; the faithful fit's epochs and threads, set here before, never acted on the worker):
about 2 s a window here, most of it fixed costs of the worker (the 200-step colour fit, the
pose fusion over its 20 s margin), plus a one-off ~5 s per worker to import torch and its optimisers.
  --quick  0.2 km vs 1 km (4 vs 13 windows): 48-55 s wall here at a load of 2.5-6 from other sessions;
  full     1 km vs 10 km (13 vs 126 windows): about 5-6 minutes.
`--behind`: the feed does not wait for the worker (the whole drive is on the bus long before it is mapped) and the
worker never skips (`mapper.lag.max_behind_m: null`): the worker as far behind as the drive is long, to show that
what it holds does not grow with its lag either; `lag_m_max` is how far behind it fell.
The two drives run side by side, each with its own worker and bus. Each worker is stopped with SIGTERM
after its feed (it drains the bus, finishes the remaining windows, writes the final map).

Memory is the worker's VmHWM, polled from /proc until it exits: its own peak. (ru_maxrss, which its
health messages report, starts from its parent's peak: execve keeps it.) Reported per drive: the peak
(final map included), the peak while driving (before SIGTERM), and the slope of the RSS sampled while
driving against the mapped distance, over the drive's second half, in MB per km.

    python bench/memory.py [--quick]     # last line: JSON with peak_rss_mb_short, peak_rss_mb_long, km_short, km_long
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from daemon.bus import pubsub  # noqa: E402
from daemon.log_format.reader import read_log  # noqa: E402
from daemon.spine.config import CarConfig, load_config  # noqa: E402
from daemon.spine.health import process_memory_mb  # noqa: E402
from daemon.spine.local_frame import LocalFrame  # noqa: E402
from daemon.spine.messages import CameraFrame, GnssFix, ImuSample, SemanticMask, WheelSpeeds  # noqa: E402
from daemon.spine.topics import GNSS_FIX, IMU, WHEEL_SPEEDS, camera_topic, health_topic, mask_topic  # noqa: E402
from mapping.live.worker_journal import read_journal  # noqa: E402

SPEED = 20.0
RADIUS = 2000.0
G = 9.80665
ORIGIN = (48.1, 11.5, 520.0)  # latitude, longitude, altitude of the drive's start
RATES_HZ = {"gnss": 10, "imu": 100, "wheels": 50, "camera": 10}
CAMERA = "front_left"
SOURCE_SECONDS = 2.0
WINDOW_M = 80.0  # before and after the centre: 160 m windows (the default), centres every 80 m
MAPPER = {"windows": {"before_m": WINDOW_M, "after_m": WINDOW_M}, "mesh": {"side_m": 0.8, "corridor_half_width_m": 4.0},
          "inputs": {"keyframe_spacing_m": 6.0}}
LEAD_M = 4 * WINDOW_M  # two windows: the next one is always fed, with the inputs beyond its end
ATTACH_S = 1.0  # the worker attaches (lossless) to new rings every 0.5 s
HWM_POLL_S = 0.02
RSS_PERIOD_S = 0.5


def car_config_data(behind: bool = False) -> dict:
    """configs/sim.yaml with one camera and no Lidar, the cheap mapper settings, a bus of its own (`behind`: a
    worker that never skips ahead)."""
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["bus"] = {"shm_prefix": f"mem{uuid.uuid4().hex[:8]}"}
    data["sensors"].pop("lidar")
    data["sensors"]["cameras"] = [c for c in data["sensors"]["cameras"] if c["name"] == CAMERA]
    data["sensors"]["can"]["dbc_file"] = str(REPO / "configs" / data["sensors"]["can"]["dbc_file"])
    data["mapper"].update(MAPPER)
    if behind:
        data["mapper"]["lag"] = {"max_behind_m": None}
    return data


def simulate_source(folder: Path) -> Path:
    """A short simulated city drive with only the camera the bench replays (in this process: no pool)."""
    from sim.drive_log import simulate_drive

    log = folder / "city.mcap"
    simulate_drive("city", SOURCE_SECONDS, log, CarConfig.model_validate(car_config_data()), seed=1, workers=1)
    return log


def city_frames(log: Path) -> list[tuple[CameraFrame, SemanticMask]]:
    """(frame, mask) pairs of the bench's camera in a simulated drive, in time order."""
    frames, masks = {}, {}
    for rec in read_log([log]):
        m = rec.message
        if isinstance(m, CameraFrame) and m.camera == CAMERA:
            frames[m.sensor_time_ns] = m
        elif isinstance(m, SemanticMask) and m.camera == CAMERA:
            masks[m.sensor_time_ns] = m
    pairs = [(frames[t], masks[t]) for t in sorted(frames) if t in masks]
    if not pairs:
        raise ValueError(f"no {CAMERA} frames with masks in {log}")
    return pairs


def vehicle_enu(t: np.ndarray) -> np.ndarray:
    """(N, 3) ENU position at drive times t (s): anticlockwise round the circle, from the origin heading east."""
    w = SPEED / RADIUS
    return np.stack([RADIUS * np.sin(w * t), RADIUS * (1 - np.cos(w * t)), np.zeros_like(t)], -1)


def antenna_enu(t: np.ndarray, lever_arm_m: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) ENU position of a GNSS antenna at `lever_arm_m` (x forward, y left, z up) from the vehicle's origin."""
    heading = SPEED / RADIUS * t
    x, y, z = lever_arm_m
    offset = np.stack([x * np.cos(heading) - y * np.sin(heading), x * np.sin(heading) + y * np.cos(heading),
                       np.full_like(t, z)], -1)
    return vehicle_enu(t) + offset


def drive_messages(km: float, pairs: list, t0_ns: int, config: CarConfig):
    """(topic, message) of the synthetic drive in time order, for the car of `config` (track width, antenna)."""
    frame = LocalFrame(*ORIGIN)
    w = SPEED / RADIUS
    rng = np.random.default_rng(0)
    seconds = km * 1000.0 / SPEED
    events = sorted((i / rate, kind) for kind, rate in RATES_HZ.items() for i in range(int(seconds * rate) + 1))
    cov = (0.02**2, 0, 0, 0, 0.02**2, 0, 0, 0, 0.05**2)
    half_track = config.vehicle.track_width_m / 2
    inner, outer = SPEED - w * half_track, SPEED + w * half_track
    lever = tuple(config.sensors.gnss.antenna_lever_arm_m)
    cursor = 0
    for t, kind in events:
        ns = t0_ns + int(round(t * 1e9))
        if kind == "gnss":
            lat, lon, alt = frame.enu_to_geodetic(antenna_enu(np.array([t]), lever) + rng.normal(0, 0.02, (1, 3)))
            yield GNSS_FIX, GnssFix(sensor_time_ns=ns, host_mono_ns=ns, latitude_deg=float(np.ravel(lat)[0]),
                                    longitude_deg=float(np.ravel(lon)[0]), altitude_m=float(np.ravel(alt)[0]),
                                    position_covariance=cov, covariance_type=2)
        elif kind == "imu":
            yield IMU, ImuSample(sensor_time_ns=ns, host_mono_ns=ns, accel_mps2=(0.0, SPEED * w, G),
                                 gyro_rps=(0.0, 0.0, w))
        elif kind == "wheels":
            yield WHEEL_SPEEDS, WheelSpeeds(sensor_time_ns=ns, host_mono_ns=ns, front_left_mps=inner,
                                            front_right_mps=outer, rear_left_mps=inner, rear_right_mps=outer,
                                            yaw_rate_rps=w)
        else:
            f, m = pairs[cursor % len(pairs)]
            cursor += 1
            yield camera_topic(CAMERA), CameraFrame(sensor_time_ns=ns, host_mono_ns=ns, camera=CAMERA,
                                                    format=f.format, data=bytes(f.data))
            yield mask_topic(CAMERA), SemanticMask(sensor_time_ns=ns, host_mono_ns=ns, camera=CAMERA,
                                                   format=m.format, data=bytes(m.data))


def mapped_m(health: pubsub.Subscriber) -> float:
    latest = health.latest()
    return json.loads(latest.detail)["mapped_until_m"] if latest is not None else 0.0


def feed(config: CarConfig, km: float, pairs: list, health: pubsub.Subscriber, lead_m: float) -> None:
    """Publish the synthetic drive into the bus, in time order, losslessly, at most `lead_m` ahead of the
    worker's mapped distance (from its health messages)."""
    pubs = {t: pubsub.open_publisher(config, t) for t in
            (GNSS_FIX, IMU, WHEEL_SPEEDS, camera_topic(CAMERA), mask_topic(CAMERA))}
    time.sleep(ATTACH_S)  # the worker registers as a lossless reader of the new rings
    t0_ns = time.monotonic_ns()
    allowed_ns = t0_ns + int(lead_m / SPEED * 1e9) if math.isfinite(lead_m) else None
    try:
        for topic, msg in drive_messages(km, pairs, t0_ns, config):
            while allowed_ns is not None and msg.host_mono_ns > allowed_ns:
                allowed_ns = t0_ns + int((mapped_m(health) + lead_m) / SPEED * 1e9)
                if msg.host_mono_ns > allowed_ns:
                    time.sleep(0.05)
            pubs[topic].publish(msg, lossless=True, timeout_s=600)
    finally:
        for p in pubs.values():
            p.close()


class RssSampler(threading.Thread):
    """Polls a worker's VmHWM until it exits, and samples its RSS with its mapped distance every RSS_PERIOD_S."""

    def __init__(self, pid: int, health: pubsub.Subscriber):
        super().__init__(name="rss-sampler", daemon=True)
        self.pid, self.health = pid, health
        self.samples: list[tuple[float, float]] = []  # (mapped m, RSS MB)
        self.lag_m_max = 0.0  # how far behind the fed distance the worker fell
        self.peak_mb = 0.0
        self.stop = threading.Event()

    def run(self) -> None:
        next_sample = 0.0
        while not self.stop.is_set():
            try:
                status = process_memory_mb(self.pid)
            except (FileNotFoundError, ProcessLookupError):
                return
            if "VmHWM" not in status:  # exited
                return
            self.peak_mb = max(self.peak_mb, status["VmHWM"])
            if time.monotonic() >= next_sample:
                self.samples.append((mapped_m(self.health), status["VmRSS"]))
                latest = self.health.latest()
                if latest is not None and "lag_m" in latest.detail:
                    self.lag_m_max = max(self.lag_m_max, json.loads(latest.detail)["lag_m"])
                next_sample = time.monotonic() + RSS_PERIOD_S
            time.sleep(HWM_POLL_S)


def rss_slope_mb_per_km(samples: list[tuple[float, float]], from_m: float) -> float | None:
    """Least-squares slope of RSS against mapped distance, over the samples mapped from `from_m` on."""
    pts = np.array([(m, r) for m, r in samples if m >= from_m])
    if len(pts) < 4 or np.ptp(pts[:, 0]) < 1.0:
        return None
    return round(float(np.polyfit(pts[:, 0] / 1000.0, pts[:, 1], 1)[0]), 2)


def run_drive(km: float, pairs: Future, lead_m: float, keep: bool, behind: bool = False) -> dict:
    """Start a worker, feed it a drive of `km`, stop it; its memory and timings."""
    folder = Path(tempfile.mkdtemp(prefix="roadlog-mem-"))
    data = car_config_data(behind)
    data["recorder"]["output_dir"] = str(folder / "data")
    config_path = folder / "car.yaml"
    config_path.write_text(yaml.safe_dump(data))
    config = load_config(config_path)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    started = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "mapping.live.mapping_worker", "--config", str(config_path),
                             "--stop-timeout-s", "0"], cwd=REPO, env=env, stdout=open(folder / "worker.log", "wb"),
                            stderr=subprocess.STDOUT)
    sampler = None
    try:
        health = pubsub.open_subscriber(config, health_topic("mapper"), wait_s=120)
        while (first := health.latest()) is None or first.state == "starting":  # loading torch: not yet listening
            time.sleep(0.1)
        up_s = time.monotonic() - started
        sampler = RssSampler(proc.pid, pubsub.open_subscriber(config, health_topic("mapper")))
        sampler.start()
        feed(config, km, pairs.result(), health, lead_m)
        fed_s = time.monotonic() - started
        driving = list(sampler.samples)
        driving_mb = sampler.peak_mb
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=3600)
        sampler.join()
        if rc != 0:
            raise RuntimeError(f"worker exited {rc}: {(folder / 'worker.log').read_text()[-2000:]}")
        last = json.loads(health.latest().detail)
        journal = read_journal(folder / "data" / "map")
        walls = [w.wall_s for w in journal.windows if w.wall_s is not None]
        (folder / "rss_samples.json").write_text(json.dumps(sampler.samples))
        return {"km": km, "peak_rss_mb": round(sampler.peak_mb, 1), "peak_rss_mb_driving": round(driving_mb, 1),
                "rss_slope_mb_per_km": rss_slope_mb_per_km(driving, km * 500.0),
                "windows": len(journal.windows),
                "windows_failed": sum(w.status == "failed" for w in journal.windows),
                "windows_skipped": sum(w.status == "skipped" for w in journal.windows),
                "lag_m_max": round(sampler.lag_m_max, 1),
                "distance_m": last["distance_m"], "bus_lost": last["bus_lost"], "errors": last["errors"],
                "startup_s": round(up_s, 1), "feed_s": round(fed_s - up_s, 1),
                "finish_s": round(time.monotonic() - started - fed_s, 1),
                "wall_s": round(time.monotonic() - started, 1),
                "window_wall_s_median": round(float(np.median(walls)), 3) if walls else None,
                "folder": str(folder) if keep else None}
    finally:
        if sampler is not None:
            sampler.stop.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        pubsub.unlink_all(config)
        if not keep:
            shutil.rmtree(folder, ignore_errors=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="0.2 km vs 1 km (full: 1 km vs 10 km)")
    parser.add_argument("--km", type=float, nargs=2, metavar=("SHORT", "LONG"), help="other drive lengths")
    parser.add_argument("--lead-m", type=float, default=LEAD_M,
                        help=f"how far the feed may run ahead of the mapped distance (default {LEAD_M:g} m)")
    parser.add_argument("--behind", action="store_true",
                        help="the feed never waits for the worker, which never skips: memory with the lag")
    parser.add_argument("--drive-log", type=Path, help="a simulated drive (with the bench's camera) to replay")
    parser.add_argument("--keep", action="store_true", help="keep each worker's folder (map, log, RSS samples)")
    args = parser.parse_args()
    started = time.monotonic()
    km_short, km_long = args.km or ((0.2, 1.0) if args.quick else (1.0, 10.0))
    source = Path(tempfile.mkdtemp(prefix="roadlog-mem-drive-"))
    try:
        with ThreadPoolExecutor(3) as pool:  # the workers start (imports) while the source drive is simulated
            pairs = pool.submit(lambda: city_frames(args.drive_log or simulate_source(source)))
            lead_m = float("inf") if args.behind else args.lead_m
            short_run = pool.submit(run_drive, km_short, pairs, lead_m, args.keep, args.behind)
            long_run = pool.submit(run_drive, km_long, pairs, lead_m, args.keep, args.behind)
            short = short_run.result()
            print(json.dumps({"short": short}), flush=True)
            long = long_run.result()
            print(json.dumps({"long": long}), flush=True)
    finally:
        shutil.rmtree(source, ignore_errors=True)
    print(json.dumps({"peak_rss_mb_short": short["peak_rss_mb"], "peak_rss_mb_long": long["peak_rss_mb"],
                      "km_short": km_short, "km_long": km_long,
                      "ratio_long_short": round(long["peak_rss_mb"] / short["peak_rss_mb"], 3),
                      "peak_rss_mb_driving_short": short["peak_rss_mb_driving"],
                      "peak_rss_mb_driving_long": long["peak_rss_mb_driving"],
                      "rss_slope_mb_per_km_long": long["rss_slope_mb_per_km"],
                      "windows_short": short["windows"], "windows_long": long["windows"],
                      "lag_m_max_short": short["lag_m_max"], "lag_m_max_long": long["lag_m_max"],
                      "window_m": 2 * WINDOW_M, "lead_m": None if args.behind else args.lead_m,
                      "wall_s": round(time.monotonic() - started, 1)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
