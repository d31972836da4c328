"""The camera driver process of the device backends (opencv, depthai): one camera's frames onto the bus, run in the
camera process (drivers.camera.camera_process)."""

from __future__ import annotations

import threading

from daemon.spine.config import CameraConfig, CarConfig, ConfigError
from daemon.spine.health import HealthCounters
from drivers.camera.camera_process import FrameSource, camera_process_main


def open_frame_source(config: CameraConfig, stop: threading.Event, health: HealthCounters) -> FrameSource:
    """The configured device backend's frames (opencv or depthai; the simulator's playback is sim.camera_playback)."""
    if config.backend == "opencv":
        from drivers.camera.opencv_camera import opencv_frames

        return opencv_frames(config, stop, health)
    if config.backend == "depthai":
        from drivers.camera.depthai_camera import depthai_frames

        return depthai_frames(config, stop, health)
    if config.backend == "recorded":
        raise ConfigError(f"camera {config.name}: backend 'recorded' has no live driver (its frames exist only in "
                          f"logs: replay or reconstruct them)")
    raise ConfigError(f"camera {config.name}: backend {config.backend!r} is played by sim.camera_playback, "
                      f"not by the device camera driver")


def check_config(car: CarConfig, config_path: str) -> None:
    """What a live run needs of the cameras (run by `roadlog check-config`): each has a live backend."""
    recorded = [c.name for c in car.sensors.cameras if c.backend == "recorded"]
    if recorded:
        raise ConfigError(f"sensors.cameras: {', '.join(recorded)} have backend 'recorded': no live driver runs "
                          f"them (replay or reconstruct their logs instead)")


def main(argv: list[str] | None = None) -> int:
    return camera_process_main(argv, lambda config, stop, health, _: open_frame_source(config, stop, health))


if __name__ == "__main__":
    raise SystemExit(main())
