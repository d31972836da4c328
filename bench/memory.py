"""Peak memory of the mapping worker for a short and a long drive: does it stay flat with the drive's length?

Simulating a long drive with cameras is far too slow on this machine, so the worker (the real process,
through the real bus) is fed a synthetic drive instead: a vehicle going round a 200 m-radius circle at
10 m/s, with consistent GNSS fixes (10 Hz), IMU samples (100 Hz) and wheel speeds (50 Hz) computed
from that motion, and the front_left camera's frames and masks of one short simulated city drive
(`configs/sim.yaml`) replayed cyclically at 10 Hz, restamped onto the synthetic clock. One camera, no
Lidar, 0.2 m mesh, 6 m corridor, 3 m keyframe spacing, 1 epoch: cheap windows. The
images therefore do not match the poses (the map is meaningless) but every window costs what a real one
costs. Both drives use the same mapper settings; the worker is stopped with SIGTERM after the feed and
its peak RSS (ru_maxrss, from its last health message) is reported.

    python bench/memory.py [--quick]     # last line: JSON with peak_rss_mb_short, peak_rss_mb_long, km_short, km_long
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from daemon import bus  # noqa: E402
from daemon.config import load_config  # noqa: E402
from daemon.log_format import read_log  # noqa: E402
from daemon.messages import CameraFrame, GnssFix, ImuSample, SemanticMask, WheelSpeeds  # noqa: E402
from daemon.topics import GNSS_FIX, IMU, WHEEL_SPEEDS, camera_topic, health_topic, mask_topic  # noqa: E402
from mapping.local_frame import LocalFrame  # noqa: E402

SPEED = 10.0
RADIUS = 200.0
G = 9.80665


def make_config(folder: Path, window_m: float) -> Path:
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["bus"] = {"shm_prefix": f"mem{uuid.uuid4().hex[:8]}"}
    data["sensors"].pop("lidar")
    data["sensors"]["cameras"] = [c for c in data["sensors"]["cameras"] if c["name"] == "front_left"]
    data["sensors"]["can"]["dbc_file"] = str(REPO / "configs" / data["sensors"]["can"]["dbc_file"])
    data["recorder"]["output_dir"] = str(folder / "data")
    data["mapper"].update(window_before_m=window_m, window_after_m=window_m, epochs=1, corridor_half_width_m=6.0,
                          mesh_side_m=0.2, keyframe_spacing_m=3.0)
    path = folder / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def city_frames(log: Path) -> list[tuple[str, CameraFrame, SemanticMask]]:
    """(camera, frame, mask) pairs of a simulated drive, in time order."""
    frames, masks = {}, {}
    for rec in read_log([log]):
        m = rec.message
        if isinstance(m, CameraFrame):
            frames[(m.camera, m.sensor_time_ns)] = m
        elif isinstance(m, SemanticMask):
            masks[(m.camera, m.sensor_time_ns)] = m
    keys = sorted((k for k in frames if k in masks), key=lambda k: k[1])
    return [(k[0], frames[k], masks[k]) for k in keys]


def feed(config_path: Path, km: float, pairs: list, t0_ns: int) -> None:
    """Publish the synthetic drive into the bus, in time order, losslessly."""
    config = load_config(config_path)
    frame = LocalFrame(48.1, 11.5, 520.0)
    cams = [c.name for c in config.sensors.cameras]
    pubs = {t: bus.open_publisher(config, t) for t in
            [GNSS_FIX, IMU, WHEEL_SPEEDS] + [camera_topic(c) for c in cams] + [mask_topic(c) for c in cams]}
    seconds = km * 1000.0 / SPEED
    w = SPEED / RADIUS
    events = []
    for rate, kind in ((10, "gnss"), (100, "imu"), (50, "wheels"), (10, "cams")):
        events += [(i / rate, kind) for i in range(int(seconds * rate) + 1)]
    events.sort()
    cursor = 0
    rng = np.random.default_rng(0)
    for t, kind in events:
        ns = t0_ns + int(round(t * 1e9))
        if kind == "gnss":
            enu = np.array([RADIUS * np.sin(w * t), RADIUS * (1 - np.cos(w * t)), 0.0]) + rng.normal(0, 0.02, 3)
            lat, lon, alt = frame.enu_to_geodetic(enu[None])
            cov = (0.02**2, 0, 0, 0, 0.02**2, 0, 0, 0, 0.05**2)
            msg = GnssFix(sensor_time_ns=ns, host_mono_ns=ns, latitude_deg=float(np.ravel(lat)[0]),
                          longitude_deg=float(np.ravel(lon)[0]), altitude_m=float(np.ravel(alt)[0]),
                          position_covariance=cov, covariance_type=2)
            pubs[GNSS_FIX].publish(msg, lossless=True, timeout_s=600)
        elif kind == "imu":
            msg = ImuSample(sensor_time_ns=ns, host_mono_ns=ns, accel_mps2=(0.0, SPEED * w, G), gyro_rps=(0.0, 0.0, w))
            pubs[IMU].publish(msg, lossless=True, timeout_s=600)
        elif kind == "wheels":
            msg = WheelSpeeds(sensor_time_ns=ns, host_mono_ns=ns, front_left_mps=SPEED * (1 - 0.8 * w / SPEED),
                              front_right_mps=SPEED * (1 + 0.8 * w / SPEED), rear_left_mps=SPEED - 0.8 * w,
                              rear_right_mps=SPEED + 0.8 * w, yaw_rate_rps=w)
            pubs[WHEEL_SPEEDS].publish(msg, lossless=True, timeout_s=600)
        else:
            for cam in cams:
                while pairs[cursor % len(pairs)][0] != cam:
                    cursor += 1
                _, f, m = pairs[cursor % len(pairs)]
                cursor += 1
                pubs[camera_topic(cam)].publish(CameraFrame(sensor_time_ns=ns, host_mono_ns=ns, camera=cam,
                                                            format=f.format, data=bytes(f.data)),
                                                lossless=True, timeout_s=600)
                pubs[mask_topic(cam)].publish(SemanticMask(sensor_time_ns=ns, host_mono_ns=ns, camera=cam,
                                                           format=m.format, data=bytes(m.data)),
                                              lossless=True, timeout_s=600)
    for p in pubs.values():
        p.close()


def run_drive(km: float, window_m: float, pairs: list) -> dict:
    folder = Path(tempfile.mkdtemp(prefix="roadlog-mem-"))
    config_path = make_config(folder, window_m)
    config = load_config(config_path)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    started = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "mapping.mapping_worker", "--config", str(config_path)],
                            cwd=REPO, env=env, stdout=open(folder / "worker.log", "wb"), stderr=subprocess.STDOUT)
    try:
        health = bus.open_subscriber(config, health_topic("mapper"), wait_s=120)
        time.sleep(1.5)  # the worker attaches to the rings (start=oldest) as they appear
        feed(config_path, km, pairs, t0_ns=time.monotonic_ns())
        fed_s = time.monotonic() - started
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=3600)
        last = json.loads(health.latest().detail)
        if rc != 0:
            raise RuntimeError(f"worker exited {rc}: {(folder / 'worker.log').read_text()[-2000:]}")
        journal = json.loads((folder / "data" / "map" / "journal.json").read_text())
        return {"km": km, "peak_rss_mb": last["peak_rss_mb"], "windows": len(journal["windows"]),
                "windows_failed": sum(w["status"] != "done" for w in journal["windows"]),
                "distance_m": last["distance_m"], "feed_s": round(fed_s, 1),
                "wall_s": round(time.monotonic() - started, 1),
                "window_wall_s_median": float(np.median([w["wall_s"] for w in journal["windows"] if "wall_s" in w]))}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        bus.unlink_all(config)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="0.1 km vs 0.3 km with 20 m windows")
    parser.add_argument("--drive-log", type=Path, help="a simulated drive to take camera frames from")
    args = parser.parse_args()
    log = args.drive_log
    if log is None:
        from drivers.sim.drive_log import simulate_drive

        log = Path(tempfile.mkdtemp(prefix="roadlog-mem-drive-")) / "city.mcap"
        simulate_drive("city", 2.0, log, load_config(REPO / "configs" / "sim.yaml"), seed=1)
    pairs = city_frames(log)
    km_short, km_long, window_m = (0.1, 0.3, 10.0) if args.quick else (0.5, 2.0, 40.0)
    short = run_drive(km_short, window_m, pairs)
    print(json.dumps({"short": short}), flush=True)
    long = run_drive(km_long, window_m, pairs)
    print(json.dumps({"long": long}), flush=True)
    print(json.dumps({"peak_rss_mb_short": short["peak_rss_mb"], "peak_rss_mb_long": long["peak_rss_mb"],
                      "km_short": km_short, "km_long": km_long, "window_m": 2 * window_m,
                      "windows_short": short["windows"], "windows_long": long["windows"],
                      "ratio_long_short": round(long["peak_rss_mb"] / short["peak_rss_mb"], 3)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
