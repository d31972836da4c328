"""The real camera processes, read back from the bus: `python -m drivers.camera.camera_driver` (opencv backend) and
`python -m sim.camera_playback` (the sim backend)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import cv2
import numpy as np
import yaml

from daemon.bus import pubsub
from daemon.log_format.writer import LogWriter
from daemon.spine.config import load_config
from daemon.spine.messages import CameraFrame, SemanticMask
from daemon.spine.topics import camera_topic, health_topic, mask_topic

ROOT = Path(__file__).resolve().parents[2]
N, PERIOD_NS = 12, 100_000_000


def write_config(tmp_path: Path, camera_update: dict) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"]["shm_prefix"] = f"t{uuid.uuid4().hex[:12]}"
    for cam in data["sensors"]["cameras"]:
        if cam["name"] == "front_left":
            cam.update(camera_update)
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def read_all(sub, until_exit: subprocess.Popen, timeout_s: float = 20.0, expect: int | None = None) -> list:
    out, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline and (expect is None or len(out) < expect):
        msg = sub.read(timeout_s=0.2, copy=True)
        if msg is not None:
            out.append(msg)
        elif until_exit.poll() is not None:
            break
    return out


def run_camera(module: str, config_path: Path, *extra: str):
    car = load_config(config_path)
    proc = subprocess.Popen([sys.executable, "-m", module, "--config", str(config_path),
                             "--camera", "front_left", *extra], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        frames = pubsub.open_subscriber(car, camera_topic("front_left"), start="oldest", wait_s=20)
        masks = pubsub.open_subscriber(car, mask_topic("front_left"), start="oldest", wait_s=5)
        health = pubsub.open_subscriber(car, health_topic("camera_front_left"), start="oldest", wait_s=5)
        got_frames = read_all(frames, proc, expect=N)
        time.sleep(1.5)
        stayed_up = proc.poll() is None  # a camera does not exit at the end of its input (sim) ...
        if stayed_up:
            proc.send_signal(signal.SIGTERM)  # ... it stops when told to
        out, err = proc.communicate(timeout=20)
        return proc.returncode, out, err, got_frames, read_all(masks, proc, 1), read_all(health, proc, 1), stayed_up
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        pubsub.unlink_all(car)


def test_sim_camera_process_plays_its_log_onto_the_bus(tmp_path):
    config_path = write_config(tmp_path, {"device": "drive.mcap"})  # relative to the config's folder
    car = load_config(config_path)
    with LogWriter(tmp_path / "drive.mcap", car) as log:
        for i in range(N):
            t = 1_000_000_000 + i * PERIOD_NS
            img = np.full((360, 640, 3), 20 * i, np.uint8)
            log.write(camera_topic("front_left"), CameraFrame(i, t, t, "front_left", "jpeg", 0, 0,
                                                              cv2.imencode(".jpg", img)[1].tobytes()))
            log.write(mask_topic("front_left"), SemanticMask(i, t, t, "front_left", "png",
                                                             cv2.imencode(".png", img[:, :, 0])[1].tobytes()))
    code, out, err, frames, masks, health, stayed_up = run_camera("sim.camera_playback", config_path)
    assert code == 0, err
    assert stayed_up
    assert len(frames) == N and len(masks) == N and f"received={2 * N} published={2 * N}" in out
    assert [f.seq for f in frames] == list(range(N))
    assert [f.sensor_time_ns - frames[0].sensor_time_ns for f in frames] == [i * PERIOD_NS for i in range(N)]
    assert [m.sensor_time_ns for m in masks] == [f.sensor_time_ns for f in frames]
    assert all(0 <= f.host_mono_ns - f.sensor_time_ns < 1_000_000_000 for f in frames)  # host clock, after stamping
    levels = [int(cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_GRAYSCALE).mean()) for f in frames]
    assert all(abs(level - 20 * i) <= 2 for i, level in enumerate(levels))
    assert health and health[-1].process == "camera_front_left" and health[-1].published == 2 * N


def test_opencv_camera_process_with_a_device_override(tmp_path):
    video = tmp_path / "cam.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 360))
    for i in range(N):
        writer.write(np.full((360, 640, 3), 15 * i, np.uint8))
    writer.release()
    config_path = write_config(tmp_path, {"backend": "opencv", "device": "/dev/video_absent"})
    code, out, err, frames, masks, health, _ = run_camera("drivers.camera.camera_driver", config_path,
                                                          "--device", str(video))
    assert code == 0, err
    assert len(frames) == N and not masks
    assert [f.sensor_time_ns for f in frames] == [i * PERIOD_NS for i in range(N)]
    assert all(f.format == "jpeg" for f in frames) and health[-1].errors == 0
