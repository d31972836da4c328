"""The camera process every camera backend runs in (one per camera): arguments, bus, signals and health.

Frames go to `camera/<name>` (encoded as the car logs them, with the sensor time), the simulator's
semantic masks to `mask/<name>`, and the process's health to `health/camera_<name>` once a second from
a thread of its own (so a stalled device still shows up as stalled). The frames come from a backend: the
devices' (drivers.camera.camera_driver) or the simulator's playback (sim.camera_playback).
"""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable, Generator

from daemon.spine.config import CameraConfig, ConfigError, load_config, reports_config_errors, resolve_path
from daemon.spine.health import HealthCounters
from daemon.spine.messages import CameraFrame, SemanticMask
from daemon.spine.process_logging import setup_logging
from daemon.spine.stop_signals import set_on_signals
from daemon.spine.topics import camera_process, camera_topic, health_topic, mask_topic

Publish = Callable[[str, object], None]
FrameSource = Generator[CameraFrame | SemanticMask, None, None]


def _health_loop(publish: Publish, health: HealthCounters, lock: threading.Lock, done: threading.Event,
                 period_s: float) -> None:
    while not done.wait(period_s):
        with lock:
            snapshot = health.snapshot()
        publish(health_topic(health.process), snapshot)


def run_camera_driver(config: CameraConfig, frames: FrameSource, publish: Publish, stop: threading.Event,
                      health: HealthCounters, *, health_period_s: float = 1.0) -> None:
    """Publish every frame and mask until the source ends or `stop` is set; health every period."""
    lock = threading.Lock()
    done = threading.Event()
    reporter = threading.Thread(target=_health_loop, args=(publish, health, lock, done, health_period_s),
                                name=f"health-{config.name}", daemon=True)
    reporter.start()
    frame_topic, masks_topic = camera_topic(config.name), mask_topic(config.name)
    try:
        for message in frames:
            publish(masks_topic if isinstance(message, SemanticMask) else frame_topic, message)
            with lock:
                health.count_published()
            if stop.is_set():
                break
    except Exception as exc:
        with lock:
            health.count_error(f"{type(exc).__name__}: {exc}")
        raise
    finally:
        frames.close()
        done.set()
        reporter.join()
        with lock:
            snapshot = health.snapshot()
        publish(health_topic(health.process), snapshot)


OpenSource = Callable[[CameraConfig, threading.Event, HealthCounters, argparse.Namespace], FrameSource]


@reports_config_errors
def camera_process_main(argv: list[str] | None, open_source: OpenSource, *, stay_up_at_end: bool = False,
                        add_arguments: Callable[[argparse.ArgumentParser], None] = lambda _: None,
                        description: str = "roadlog camera driver: one camera's frames onto the bus") -> int:
    """One camera process: parse the arguments, open the bus, publish what open_source gives until stopped.
    stay_up_at_end: keep reporting health once the source ends (a played log), instead of exiting."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--camera", required=True, help="camera name in sensors.cameras")
    parser.add_argument("--device", help="override the camera's device (V4L2 path, pipeline, serial, .mcap)")
    add_arguments(parser)
    args = parser.parse_args(argv)
    setup_logging(camera_process(args.camera))

    from daemon.bus.pubsub import open_publisher

    car = load_config(args.config)
    try:
        config = car.camera(args.camera)
    except KeyError as exc:
        raise ConfigError(f"{args.config}: {exc.args[0]}") from None
    device = args.device if args.device is not None else config.device
    if config.backend == "sim" and device:
        device = str(resolve_path(args.config, device))
    config = config.model_copy(update={"device": device})
    process = camera_process(config.name)
    publishers = {t: open_publisher(car, t) for t in
                  (camera_topic(config.name), mask_topic(config.name), health_topic(process))}
    health = HealthCounters(process, expected_rate_hz=config.rate_hz)
    stop = threading.Event()
    set_on_signals(stop)
    frames = open_source(config, stop, health, args)
    run_camera_driver(config, frames, lambda t, m: publishers[t].publish(m), stop, health)
    if stay_up_at_end:
        while not stop.wait(1.0):
            publishers[health_topic(process)].publish(health.snapshot())
    print(f"camera {config.name} stopped: received={health.received} published={health.published} "
          f"dropped={health.dropped} errors={health.errors}", flush=True)
    return 0
