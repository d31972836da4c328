"""The sim camera backend: one camera's frames and masks played from a drive log (MCAP) at real rate."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from daemon.log_format.writer import LogWriter
from daemon.spine.config import ConfigError, load_config
from daemon.spine.health import HealthCounters
from daemon.spine.messages import CameraFrame, SemanticMask
from daemon.spine.topics import camera_topic, mask_topic
from drivers.camera.camera_process import run_camera_driver
from sim.camera_playback import sim_frames

CONFIG_FILE = Path(__file__).resolve().parents[2] / "configs" / "sim.yaml"
N, PERIOD_NS, T0 = 15, 100_000_000, 7_000_000_000


def image(i: int, w: int, h: int) -> np.ndarray:
    out = np.full((h, w, 3), 50, np.uint8)
    out[:, 20 * i: 20 * i + 20] = (220, 120, 40)  # BGR
    return out


def column(img: np.ndarray) -> int:
    return int(np.argmax(img[img.shape[0] // 2, : 20 * N, 1].reshape(N, 20).mean(axis=1)))


def write_drive(path: Path, raw: bool = False, metadata: dict[str, str] | None = None) -> None:
    car = load_config(CONFIG_FILE)
    with LogWriter(path, car, metadata) as log:
        for i in range(N):
            t = T0 + i * PERIOD_NS
            for cam in ("front_left", "front_right"):
                w, h = car.camera(cam).width, car.camera(cam).height
                img = image(i if cam == "front_left" else N - 1 - i, w, h)
                if raw:
                    frame = CameraFrame(i, t, t + 30_000_000, cam, "rgb8", w, h, img[:, :, ::-1].tobytes())
                else:
                    frame = CameraFrame(i, t, t + 30_000_000, cam, "jpeg", 0, 0,
                                        cv2.imencode(".jpg", img)[1].tobytes())
                log.write(camera_topic(cam), frame)
                mask = np.full((h, w), i % 7, np.uint8)
                log.write(mask_topic(cam), SemanticMask(i, t, t + 40_000_000, cam, "png",
                                                        cv2.imencode(".png", mask)[1].tobytes()))


def play(path: Path, start_mono_ns: int | None, stop_after_s: float | None = None, loop: bool = False):
    config = load_config(CONFIG_FILE).camera("front_left").model_copy(update={"device": str(path), "loop": loop})
    stop = threading.Event()
    if stop_after_s is not None:
        threading.Timer(stop_after_s, stop.set).start()
    health = HealthCounters("camera_front_left", expected_rate_hz=config.rate_hz)
    published: list = []
    frames = sim_frames(config, stop, health, start_mono_ns=start_mono_ns)
    run_camera_driver(config, frames, lambda t, m: published.append((t, m, time.monotonic_ns())), stop, health)
    return published, health


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sim") / "drive.mcap"
    write_drive(path)
    return path


def test_frames_and_masks_of_one_camera_at_real_rate(drive):
    start = time.monotonic_ns() + 200_000_000
    published, health = play(drive, start)
    frames = [(m, at) for t, m, at in published if t == camera_topic("front_left")]
    masks = [(m, at) for t, m, at in published if t == mask_topic("front_left")]
    assert len(frames) == N and len(masks) == N
    assert {t for t, _, _ in published} == {camera_topic("front_left"), mask_topic("front_left"),
                                            "health/camera_front_left"}
    for i, ((f, at), (m, _)) in enumerate(zip(frames, masks, strict=True)):
        assert f.sensor_time_ns == start + i * PERIOD_NS == m.sensor_time_ns  # on the host monotonic clock
        # delivered when due, not before; later than two periods it would have been dropped (margin for a loaded CI)
        assert 0 <= at - f.sensor_time_ns < 300_000_000
        assert f.format == "jpeg" and f.camera == "front_left" and f.seq == 0 and f.host_mono_ns == 0
        assert column(cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)) == i
        assert (cv2.imdecode(np.frombuffer(m.data, np.uint8), cv2.IMREAD_UNCHANGED) == i % 7).all()
    assert health.received == 2 * N and health.published == 2 * N and health.dropped == 0


def test_a_start_in_the_past_drops_what_is_already_late(drive):
    start = time.monotonic_ns() - 700_000_000
    published, health = play(drive, start)
    frames = [m for t, m, _ in published if t == camera_topic("front_left")]
    # frames 0..4 are more than two periods (200 ms) late at once; a frame or so more on a slow machine
    assert 4 <= N - len(frames) <= 7
    assert health.dropped == 2 * (N - len(frames))
    assert frames[-1].sensor_time_ns == start + (N - 1) * PERIOD_NS


def test_stop_ends_the_playback(drive):
    t0 = time.monotonic()
    published, _ = play(drive, time.monotonic_ns(), stop_after_s=0.45)
    assert time.monotonic() - t0 < 1.0
    assert 4 <= sum(t == camera_topic("front_left") for t, _, _ in published) <= 6


def test_raw_frames_in_the_log_are_delivered_as_jpeg(tmp_path):
    path = tmp_path / "raw.mcap"
    write_drive(path, raw=True)
    start = time.monotonic_ns() + 100_000_000
    published, health = play(path, start)
    frames = [m for t, m, _ in published if t == camera_topic("front_left")]
    assert len(frames) == N and health.dropped == 0 and health.rejected == 0
    for i, f in enumerate(frames):
        decoded = cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)
        assert f.format == "jpeg" and f.width == 0 and decoded.shape == (360, 640, 3)
        assert column(decoded) == i and f.sensor_time_ns == start + i * PERIOD_NS
        assert np.abs(decoded[180, 20 * i + 10].astype(int) - (220, 120, 40)).max() < 15  # rgb8 is RGB, not BGR


def test_a_missing_log_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="nope.mcap does not exist"):
        play(tmp_path / "nope.mcap", None)
    with pytest.raises(ConfigError, match="needs `device`"):
        play("", None)


def test_a_looping_camera_plays_its_drive_again_with_its_times_carried_on(tmp_path):
    path = tmp_path / "looped.mcap"
    write_drive(path, metadata={"seconds": str(N * PERIOD_NS / 1e9)})  # what `roadlog simulate` records
    start = time.monotonic_ns() - 1_200_000_000  # frames 0..9 of the first pass already late: dropped
    published, health = play(path, start, stop_after_s=1.6, loop=True)
    frames = [m for t, m, _ in published if t == camera_topic("front_left")]
    shown = [column(cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)) for f in frames]
    assert shown[:3] == [10, 11, 12] or shown[:3] == [11, 12, 13]  # (a frame more dropped on a slow machine)
    wrap = shown.index(0)
    assert shown[wrap - 1] == N - 1 and shown[wrap:wrap + 5] == [0, 1, 2, 3, 4]  # the second pass, from its start
    times = [f.sensor_time_ns for f in frames]
    assert np.all(np.diff(times) == PERIOD_NS)  # one camera's rhythm across the end of a pass
    assert times[wrap] == start + N * PERIOD_NS
    assert health.dropped == 2 * 10 or health.dropped == 2 * 11


def test_looping_a_log_that_is_not_a_simulated_drive_is_a_config_error(drive):
    with pytest.raises(ConfigError, match="cannot be looped"):
        play(drive, None, loop=True)


def test_only_a_sim_camera_loops():
    data = load_config(CONFIG_FILE).camera("front_left").model_dump()
    data.update(backend="opencv", loop=True)
    with pytest.raises(ValueError, match="only a sim camera"):
        type(load_config(CONFIG_FILE).camera("front_left")).model_validate(data)
