"""Recorder CPU and write rate with the full simulated car at real rate; replay speed in max mode.

A publisher process plays the car's sensors onto the bus at their real rates with payloads of real
sizes (3 cameras at 10 Hz with 100-300 KB incompressible "JPEG" frames, Lidar 640 packets/s of
24,896 B, IMU 100 Hz, GNSS 10 Hz, CAN 1.5 kHz) while the real recorder process records them. Then the
recorded segments are read back (read_log alone) and replayed into the bus in max mode.

    python bench/recorder.py [--quick] [--seconds S]

Last line: JSON with recorder_cpu_pct (% of one core), write_mb_s, lost, read_x_realtime and
replay_x_realtime (recorded duration / wall time).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import psutil
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.bus import pubsub  # noqa: E402
from daemon.log_format.reader import read_log, read_metadata  # noqa: E402
from daemon.processes.replay import replay  # noqa: E402
from daemon.spine.config import load_config  # noqa: E402
from daemon.spine.messages import CameraFrame, CanFrame, GnssFix, ImuSample, LidarPacket  # noqa: E402
from daemon.spine.topics import CAN_FRAMES, GNSS_FIX, IMU, LIDAR_PACKETS, camera_topic, health_topic  # noqa: E402

CAN_RATE_HZ = 1500.0
TICK_S = 0.005


def streams(config) -> dict[str, float]:
    """topic -> rate (Hz) of the simulated car."""
    rates = {camera_topic(c.name): c.rate_hz for c in config.sensors.cameras}
    rates[LIDAR_PACKETS] = config.sensors.lidar.columns_per_frame / 16 * config.sensors.lidar.rate_hz
    rates[IMU] = config.sensors.gnss.imu_rate_hz
    rates[GNSS_FIX] = config.sensors.gnss.rate_hz
    rates[CAN_FRAMES] = CAN_RATE_HZ
    return rates


def publish_car(config_path: str, seconds: float, started, result) -> None:
    """The publisher process: every stream at its rate for `seconds`; puts (counts sent, CPU s) in `result`."""
    config = load_config(config_path)
    rng = random.Random(0)
    frames = [rng.randbytes(rng.randrange(100_000, 300_000)) for _ in range(12)]
    packets = [rng.randbytes(24_896) for _ in range(16)]
    rates = streams(config)
    pubs = {t: pubsub.open_publisher(config, t) for t in rates}
    sent = dict.fromkeys(rates, 0)
    cameras = {camera_topic(c.name): c.name for c in config.sensors.cameras}

    def message(topic: str, i: int, now: int):
        if topic in cameras:
            return CameraFrame(sensor_time_ns=now, camera=cameras[topic], format="jpeg", data=frames[i % 12])
        if topic == LIDAR_PACKETS:
            return LidarPacket(sensor_time_ns=now, data=packets[i % 16])
        if topic == IMU:
            return ImuSample(sensor_time_ns=now, accel_mps2=(0.1, 0.0, 9.81), gyro_rps=(0.0, 0.0, 0.01))
        if topic == GNSS_FIX:
            return GnssFix(sensor_time_ns=now, latitude_deg=48.1, longitude_deg=11.5, altitude_m=520.0)
        return CanFrame(sensor_time_ns=now, arbitration_id=0x100 + i % 40, channel="can0", data=packets[0][:8])

    cpu0 = time.process_time()
    started.set()
    start = time.monotonic()
    while (elapsed := time.monotonic() - start) < seconds:
        now = time.monotonic_ns()
        for topic, rate in rates.items():
            due = int(elapsed * rate)
            while sent[topic] < due:
                pubs[topic].publish(message(topic, sent[topic], now))
                sent[topic] += 1
        time.sleep(max(0.0, TICK_S - (time.monotonic() - start - elapsed)))
    for p in pubs.values():
        p.close()
    result.put((sent, time.process_time() - cpu0))


def record(config_path: Path, out: Path, seconds: float) -> dict:
    config = load_config(config_path)
    rec = subprocess.Popen([sys.executable, "-m", "daemon.processes.recorder", "--config", str(config_path),
                            "--output-dir", str(out)], cwd=ROOT, stderr=subprocess.DEVNULL)
    health = pubsub.open_subscriber(config, health_topic("recorder"), wait_s=30)
    assert health.read(timeout_s=30) is not None, "recorder did not start"
    ctx = multiprocessing.get_context("spawn")
    result, started = ctx.Queue(), ctx.Event()
    publisher = ctx.Process(target=publish_car, args=(str(config_path), seconds, started, result))
    proc = psutil.Process(rec.pid)
    publisher.start()
    started.wait(timeout=60)
    cpu0 = proc.cpu_times()
    sent, pub_cpu_s = result.get(timeout=seconds + 60)
    published_at = time.monotonic()
    publisher.join()
    written: dict[str, int] = {}
    while any(written.get(t, 0) < n for t, n in sent.items()) and time.monotonic() - published_at < 120:
        msg = health.read(timeout_s=2)  # the recorder catches up with what is still in the rings
        if msg is not None:
            written = json.loads(msg.detail)["written"]
    drain_s = time.monotonic() - published_at
    cpu1 = proc.cpu_times()
    rec.send_signal(signal.SIGTERM)
    rc = rec.wait(timeout=60)
    health.close()
    written, lost = {}, {}
    segments = sorted(out.glob("*.mcap"))
    for s in segments:
        counts = read_metadata(s)["roadlog.counts"]
        for t, n in json.loads(counts["messages_per_topic"]).items():
            written[t] = written.get(t, 0) + n
        for t, n in json.loads(counts["lost_per_topic"]).items():
            lost[t] = lost.get(t, 0) + n
    total_bytes = sum(s.stat().st_size for s in segments)
    return {
        "recorder_rc": rc,
        # CPU time the recorder spent on the drive (catching up included) per second of drive
        "recorder_cpu_pct": 100 * ((cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)) / seconds,
        "publisher_cpu_pct": 100 * pub_cpu_s / seconds,
        "catch_up_s": drain_s,  # after the drive ended, until the last message was written
        "write_mb_s": total_bytes / 1e6 / seconds,
        "segments": len(segments),
        "messages_sent": sum(sent.values()),
        "missing": {t: n - written.get(t, 0) for t, n in sent.items() if written.get(t, 0) != n},
        "lost": lost,
        "segment_paths": segments,
    }


def read_and_replay(config_path: Path, segments: list[Path]) -> dict:
    """Log reading alone, then replay into the bus at max rate, as multiples of the drive's duration."""
    config = load_config(config_path)
    drive_topics = set(streams(config))
    first = last = None
    n = 0
    t = time.perf_counter()
    for rec in read_log(segments):
        n += 1
        if rec.topic in drive_topics:
            first = rec.log_time_ns if first is None else first
            last = rec.log_time_ns
    read_s = time.perf_counter() - t
    duration_s = (last - first) / 1e9
    progress = replay(config, segments, rate=None)
    return {
        "drive_duration_s": duration_s,
        "log_messages": n,
        "read_msgs_per_s": n / read_s,
        "read_x_realtime": duration_s / read_s,
        "replay_x_realtime": duration_s / progress.wall_s,
        "replay_msgs_per_s": sum(progress.published.values()) / progress.wall_s,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a 12 s recording (under a minute in all)")
    parser.add_argument("--seconds", type=float, default=None, help="recording length (default 60, quick 12)")
    args = parser.parse_args(argv)
    seconds = args.seconds or (12.0 if args.quick else 60.0)
    work = Path(tempfile.mkdtemp(prefix="roadlog_bench_"))
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"]["shm_prefix"] = f"bench{uuid.uuid4().hex[:8]}"
    data["recorder"].update(segment_seconds=min(20.0, seconds / 2), min_free_gib=1.0, min_free_pct=1.0)
    config_path = work / "car.yaml"
    config_path.write_text(yaml.safe_dump(data))
    try:
        rec = record(config_path, work / "logs", seconds)
        segments = rec.pop("segment_paths")
        figures = {"seconds": seconds, **rec, **read_and_replay(config_path, segments)}
    finally:
        pubsub.unlink_all(load_config(config_path))
        shutil.rmtree(work, ignore_errors=True)
    for k, v in figures.items():
        print(f"{k:>20}: {round(v, 2) if isinstance(v, float) else v}", file=sys.stderr)
    print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in figures.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
