"""Bus throughput and latency between real processes.

(1) Three camera writer processes publish raw 4K frames (3840x2160x3 = 24.9 MB) at 30 Hz each,
    losslessly, to two lossless subscriber processes each (9 processes): frames lost, publish-to-read
    latency (host_mono_ns, set as publish starts, to the read returning), publish time, late frames.
(2) Large-payload throughput, one writer and one reader process, 25 MB frames back to back
    (lossless), as a ratio to a plain numpy memcpy of the same bytes measured in the same run;
    once with a zero-copy reader and once with a reader that copies every frame out.
(3) 1 KB messages per second, one writer and one reader process (lossless, so none are lost).
(4) Wake-up latency of a waiting reader process: small messages published at 500 Hz.

    python bench/bus.py [--quick]

Last line: JSON with lost, latency_ms_median, memcpy_ratio, small_msgs_per_s and the details.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.bus.pubsub import open_publisher, open_subscriber, unlink_all  # noqa: E402
from daemon.spine.config import load_config  # noqa: E402
from daemon.spine.messages import CameraFrame, LidarPacket  # noqa: E402
from daemon.spine.topics import LIDAR_PACKETS, camera_topic  # noqa: E402

SPAWN = multiprocessing.get_context("spawn")
WIDTH, HEIGHT = 3840, 2160
FRAME_BYTES = WIDTH * HEIGHT * 3
CAMERA_HZ = 30.0


def bench_config():
    """The simulated car with its three cameras at 4K and a private shared-memory prefix."""
    config = load_config(ROOT / "configs" / "sim.yaml")
    cameras = [c.model_copy(update={"width": WIDTH, "height": HEIGHT, "rate_hz": CAMERA_HZ})
               for c in config.sensors.cameras]
    sensors = config.sensors.model_copy(update={"cameras": cameras})
    bus = config.bus.model_copy(update={"shm_prefix": f"rlbench_{uuid.uuid4().hex[:8]}"})
    return config.model_copy(update={"sensors": sensors, "bus": bus})


def _camera_writer(config, camera: str, seconds: float, ready, go, results) -> None:
    pub = open_publisher(config, camera_topic(camera))
    frame = np.random.default_rng(0).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    stamp = frame.reshape(-1)[:8].view(np.uint64)
    ready.put(camera)
    go.wait()
    publish_s, late, t0 = [], 0, time.monotonic()
    n = int(seconds * CAMERA_HZ)
    for i in range(n):
        due = t0 + i / CAMERA_HZ
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        elif now - due > 0.5 / CAMERA_HZ:
            late += 1
        stamp[0] = pub.next_seq  # each frame carries its seq in its first 8 bytes
        t = time.perf_counter()
        pub.publish(CameraFrame(camera=camera, format="rgb8", width=WIDTH, height=HEIGHT, data=frame),
                    lossless=True, timeout_s=10)
        publish_s.append(time.perf_counter() - t)
    results.put({"role": "writer", "published": n, "late": late, "seconds": time.monotonic() - t0,
                 "publish_ms_median": 1e3 * statistics.median(publish_s)})


def _camera_reader(config, camera: str, count: int, ready, results) -> None:
    sub = open_subscriber(config, camera_topic(camera), start="oldest", lossless=True, wait_s=30)
    ready.put(camera)
    latencies, corrupt = [], 0
    while sub.received + sub.lost < count:
        message = sub.read(10)
        if message is None:
            break
        latencies.append(time.monotonic_ns() - message.host_mono_ns)
        if np.frombuffer(message.data[:8], np.uint64)[0] != message.seq or not sub.still_valid():
            corrupt += 1
    results.put({"role": "reader", "received": sub.received, "lost": sub.lost, "corrupt": corrupt,
                 "latencies_ns": latencies})


def three_4k_cameras(config, seconds: float) -> dict:
    cameras = [c.name for c in config.sensors.cameras]
    count = int(seconds * CAMERA_HZ)
    ready, results, go = SPAWN.Queue(), SPAWN.Queue(), SPAWN.Event()
    writers = [SPAWN.Process(target=_camera_writer, args=(config, c, seconds, ready, go, results))
               for c in cameras]
    for p in writers:
        p.start()
    for _ in writers:
        ready.get(timeout=60)  # rings exist: readers can attach
    readers = [SPAWN.Process(target=_camera_reader, args=(config, c, count, ready, results))
               for c in cameras for _ in range(2)]
    for p in readers:
        p.start()
    for _ in readers:
        ready.get(timeout=60)
    go.set()
    outcomes = [results.get(timeout=seconds + 120) for _ in writers + readers]
    for p in writers + readers:
        p.join(30)
    w = [o for o in outcomes if o["role"] == "writer"]
    r = [o for o in outcomes if o["role"] == "reader"]
    latencies_ms = np.array([x for o in r for x in o["latencies_ns"]]) / 1e6
    return {
        "frames_published": sum(o["published"] for o in w),
        "frames_read": sum(o["received"] for o in r),
        "lost": sum(o["lost"] for o in r),
        "corrupt": sum(o["corrupt"] for o in r),
        "late_frames": sum(o["late"] for o in w),
        "latency_ms_median": float(np.median(latencies_ms)),
        "latency_ms_p95": float(np.percentile(latencies_ms, 95)),
        "publish_ms_median": statistics.median(o["publish_ms_median"] for o in w),
        "achieved_hz_per_camera": statistics.mean(o["published"] / o["seconds"] for o in w),
        "write_gb_s": sum(o["published"] * FRAME_BYTES / o["seconds"] for o in w) / 1e9,
    }


def _throughput_reader(config, topic: str, count: int, copy: bool, ready, results) -> None:
    sub = open_subscriber(config, topic, start="oldest", lossless=True, wait_s=30)
    ready.put(topic)
    last_ns = 0
    while sub.received < count:
        message = sub.read(10, copy=copy)
        if message is None:
            break
        last_ns = time.monotonic_ns()
    results.put({"received": sub.received, "lost": sub.lost, "last_ns": last_ns})


def _memcpy_gb_s(src: np.ndarray, dst: np.ndarray, frames: int) -> float:
    t = time.perf_counter()
    for _ in range(frames):
        np.copyto(dst, src)
    return frames * src.nbytes / (time.perf_counter() - t) / 1e9


def large_throughput(config, frames: int, copy: bool) -> dict:
    """Bus GB/s end to end (first publish to last read) against memcpy GB/s before and after (the faster)."""
    topic = camera_topic(config.sensors.cameras[0].name)
    pub = open_publisher(config, topic)
    ready, results = SPAWN.Queue(), SPAWN.Queue()
    reader = SPAWN.Process(target=_throughput_reader, args=(config, topic, frames, copy, ready, results))
    reader.start()
    ready.get(timeout=60)
    frame = np.random.default_rng(1).integers(0, 256, FRAME_BYTES, dtype=np.uint8)
    dst = np.empty_like(frame)
    np.copyto(dst, frame)  # both buffers resident, as the ring is
    memcpy_before = _memcpy_gb_s(frame, dst, frames // 2)
    start_ns = time.monotonic_ns()
    for _ in range(frames):
        pub.publish(CameraFrame(format="rgb8", width=WIDTH, height=HEIGHT, data=frame), lossless=True,
                    timeout_s=10)
    out = results.get(timeout=120)
    reader.join(30)
    pub.close()
    bus_gb_s = frames * FRAME_BYTES / ((out["last_ns"] - start_ns) / 1e9) / 1e9
    memcpy_gb_s = max(memcpy_before, _memcpy_gb_s(frame, dst, frames // 2))
    return {"bus_gb_s": bus_gb_s, "memcpy_gb_s": memcpy_gb_s, "ratio": bus_gb_s / memcpy_gb_s,
            "lost": out["lost"], "received": out["received"]}


def _small_writer(config, seconds: float, ready, go, results) -> None:
    pub = open_publisher(config, LIDAR_PACKETS)
    data = bytes(1024)
    ready.put("writer")
    go.wait()
    end = time.monotonic() + seconds
    n = 0
    while time.monotonic() < end:
        for _ in range(100):
            pub.publish(LidarPacket(data=data), lossless=True, timeout_s=10)
        n += 100
    results.put({"role": "writer", "published": n})


def _small_reader(config, ready, results) -> None:
    sub = open_subscriber(config, LIDAR_PACKETS, start="oldest", lossless=True, wait_s=30)
    ready.put("reader")
    first = sub.read(60)
    first_ns = last_ns = first.host_mono_ns
    while sub.read(1.0) is not None:
        last_ns = time.monotonic_ns()
    results.put({"role": "reader", "received": sub.received, "lost": sub.lost,
                 "seconds": (last_ns - first_ns) / 1e9})


def small_messages(config, seconds: float) -> dict:
    ready, results, go = SPAWN.Queue(), SPAWN.Queue(), SPAWN.Event()
    open_publisher(config, LIDAR_PACKETS).close()
    writer = SPAWN.Process(target=_small_writer, args=(config, seconds, ready, go, results))
    reader = SPAWN.Process(target=_small_reader, args=(config, ready, results))
    writer.start()
    reader.start()
    ready.get(timeout=60)
    ready.get(timeout=60)
    go.set()
    outcomes = {o["role"]: o for o in (results.get(timeout=seconds + 60) for _ in range(2))}
    writer.join(30)
    reader.join(30)
    r = outcomes["reader"]
    return {"published": outcomes["writer"]["published"], "received": r["received"], "lost": r["lost"],
            "msgs_per_s": r["received"] / r["seconds"]}


def _latency_reader(config, count: int, ready, results) -> None:
    sub = open_subscriber(config, LIDAR_PACKETS, wait_s=30)
    ready.put("reader")
    latencies = []
    while len(latencies) < count and (message := sub.read(10)) is not None:
        latencies.append(time.monotonic_ns() - message.host_mono_ns)
    results.put(latencies)


def waiting_reader_latency(config, count: int) -> dict:
    pub = open_publisher(config, LIDAR_PACKETS)
    ready, results = SPAWN.Queue(), SPAWN.Queue()
    reader = SPAWN.Process(target=_latency_reader, args=(config, count, ready, results))
    reader.start()
    ready.get(timeout=60)
    time.sleep(0.1)
    for _ in range(count):
        pub.publish(LidarPacket(data=bytes(1024)))
        time.sleep(0.002)
    latencies_ms = np.array(results.get(timeout=60)) / 1e6
    reader.join(30)
    pub.close()
    return {"median_ms": float(np.median(latencies_ms)), "p95_ms": float(np.percentile(latencies_ms, 95))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="short runs (under a minute)")
    args = parser.parse_args()
    config = bench_config()
    seconds = 4.0 if args.quick else 20.0
    try:
        cams = three_4k_cameras(config, seconds)
        print(f"(1) 3 x 4K @30 Hz, 2 lossless readers each: {cams}", flush=True)
        unlink_all(config)
        frames = 20 if args.quick else 100
        zero_copy = large_throughput(config, frames, copy=False)
        print(f"(2) 25 MB frames, zero-copy reader: {zero_copy}", flush=True)
        copy_out = large_throughput(config, frames, copy=True)
        print(f"(2) 25 MB frames, reader copies out: {copy_out}", flush=True)
        unlink_all(config)
        small = small_messages(config, 3.0 if args.quick else 10.0)
        print(f"(3) 1 KB messages: {small}", flush=True)
        unlink_all(config)
        wake = waiting_reader_latency(config, 500 if args.quick else 2000)
        print(f"(4) waiting reader, 1 KB at 500 Hz: {wake}", flush=True)
    finally:
        unlink_all(config)
    print(json.dumps({
        "lost": cams["lost"] + zero_copy["lost"] + copy_out["lost"] + small["lost"],
        "latency_ms_median": round(cams["latency_ms_median"], 3),
        "latency_ms_p95": round(cams["latency_ms_p95"], 3),
        "camera_frames_published": cams["frames_published"],
        "camera_frames_read": cams["frames_read"],
        "camera_corrupt": cams["corrupt"],
        "camera_late_frames": cams["late_frames"],
        "camera_hz_achieved": round(cams["achieved_hz_per_camera"], 1),
        "camera_publish_ms_median": round(cams["publish_ms_median"], 2),
        "camera_write_gb_s": round(cams["write_gb_s"], 2),
        "memcpy_ratio": round(zero_copy["ratio"], 3),
        "memcpy_ratio_copy_out": round(copy_out["ratio"], 3),
        "bus_gb_s": round(zero_copy["bus_gb_s"], 2),
        "memcpy_gb_s": round(zero_copy["memcpy_gb_s"], 2),
        "small_msgs_per_s": round(small["msgs_per_s"]),
        "small_latency_ms_median": round(wake["median_ms"], 3),
        "small_latency_ms_p95": round(wake["p95_ms"], 3),
    }))


if __name__ == "__main__":
    main()
