"""The `sim` camera backend's process: one camera's frames and semantic masks from a simulated drive log (MCAP).

Each record is delivered at its real rate, as a camera would: the log's sensor time `log_origin_ns`
(default: this camera's first sensor time) happens at host monotonic time `start_mono_ns` (default:
now), and every frame and mask is released when its moment comes, its sensor time carried over to the
host monotonic clock (as an OAK's are). Several simulated sensors given the same origin and start time
stay in step. A record already more than two frame periods late is dropped (counted), like a camera
whose consumer fell behind. Raw frames are JPEG-encoded when the camera's encoding is jpeg; other
frames go out as logged. The stream ends with the log, or, with the camera's `loop` on, plays the log again
pass after pass (sim/drive_loop.py) until stopped.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from daemon.log_format.reader import read_log
from daemon.spine.config import CameraConfig, ConfigError
from daemon.spine.health import HealthCounters
from daemon.spine.messages import RAW_FORMAT_CHANNELS, CameraFrame, SemanticMask
from daemon.spine.topics import camera_topic, mask_topic
from drivers.camera.camera_process import camera_process_main
from drivers.camera.frame_encoding import FrameEncodingError, encode_image, raw_frame_image
from sim.drive_loop import loop_period_ns


def _as_delivered(message: CameraFrame | SemanticMask, config: CameraConfig, sensor_time_ns: int):
    if isinstance(message, CameraFrame) and message.format in RAW_FORMAT_CHANNELS and config.encoding != "raw":
        return encode_image(raw_frame_image(message), config.name, config.encoding, config.jpeg_quality,
                            sensor_time_ns)
    return dataclasses.replace(message, seq=0, host_mono_ns=0, sensor_time_ns=sensor_time_ns, camera=config.name)


def sim_frames(config: CameraConfig, stop: threading.Event, health: HealthCounters, *,
               start_mono_ns: int | None = None, log_origin_ns: int | None = None,
               ) -> Iterator[CameraFrame | SemanticMask]:
    """This camera's frames and masks from the log at config.device, paced as described above."""
    if not config.device:
        raise ConfigError(f"camera {config.name}: the sim backend needs `device`: the drive log (.mcap) to play")
    path = Path(config.device)
    if not path.is_file():
        raise ConfigError(f"camera {config.name}: sim log {path} does not exist")
    topics = [camera_topic(config.name), mask_topic(config.name)]
    records = read_log([path], topics=topics)
    first = next(records, None)
    if first is None:
        health.count_error(f"{path}: no frames of camera {config.name!r}")
        return
    origin = first.message.sensor_time_ns if log_origin_ns is None else log_origin_ns
    start = time.monotonic_ns() if start_mono_ns is None else start_mono_ns
    period_ns = loop_period_ns(path) if config.loop else 0
    late_ns = int(2e9 / config.rate_hz)
    for shift_ns in itertools.count(0, period_ns) if config.loop else (0,):
        for record in (itertools.chain([first], records) if shift_ns == 0 else read_log([path], topics=topics)):
            message = record.message
            due_ns = start + shift_ns + (message.sensor_time_ns - origin)
            wait_ns = due_ns - time.monotonic_ns()
            if wait_ns > 0 and stop.wait(wait_ns / 1e9):
                return
            if stop.is_set():
                return
            health.received += 1
            if wait_ns < -late_ns:
                health.dropped += 1
                continue
            try:
                yield _as_delivered(message, config, due_ns)
            except FrameEncodingError as exc:
                health.count_rejected(f"{record.topic}: {exc}")


def _add_pacing(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--start-mono-ns", type=int, help="host monotonic time the log origin maps to")
    parser.add_argument("--log-origin-ns", type=int, help="log sensor time played at --start-mono-ns")


def main(argv: list[str] | None = None) -> int:
    """The camera process of a `sim` camera. The simulated drive's end does not end it (the supervisor would
    replay the drive): it stays up, reporting health, until told to stop."""
    return camera_process_main(
        argv, lambda config, stop, health, args: sim_frames(config, stop, health, start_mono_ns=args.start_mono_ns,
                                                            log_origin_ns=args.log_origin_ns),
        stay_up_at_end=True, add_arguments=_add_pacing,
        description="roadlog sim camera: one camera's frames played from a simulated drive log onto the bus")


if __name__ == "__main__":
    raise SystemExit(main())
