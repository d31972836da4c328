"""The process table: which processes the daemon runs, in which mode, with what arguments.

Adding a sensor means editing this table and the topic table (daemon/spine/topics.py), nothing else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from daemon.spine.config import POINT_CLOUD_LIDAR, CarConfig, ConfigError
from daemon.spine.topics import (
    LIDAR_VIEW_PROCESS,
    TIME_ANCHOR,
    VEHICLE_POSE_PROCESS,
    camera_process,
    fuses_pose,
    health_topic,
    topic_table,
    views_lidar,
)

Mode = Literal["live", "replay"]
MAP_STOP_TIMEOUT_S = 600.0  # how long the mapper may take after SIGTERM (its remaining windows, the final map)
MAPPER_NICE = 10  # the mapper's CPU priority below the drivers' and the recorder's
VIEWER_NICE = MAPPER_NICE  # the viewing clouds' and the live pose's: as the mapper, below the drivers and the recorder
RESTARTS_ENV = "ROADLOG_RESTARTS"  # set by the supervisor: how many times it restarted this process (0: first start)
# What the daemon itself checks before it starts any process (as ProcessSpec.check): the rings it makes fit
DAEMON_CHECK = "daemon.bus.ring_space:check_rings"


@dataclass(frozen=True)
class ProcessSpec:
    name: str  # also the name it publishes health under
    module: str  # run as `python -m module *args`
    args: tuple[str, ...] = ()
    required: bool = False  # a driver that readiness waits for (required_drivers)
    heartbeat_s: float = 10.0  # restart when its health is older than this (0: not watched)
    restart_on_success: bool = True  # False: a clean exit means "done" (replay at the end of its logs)
    stop_timeout_s: float = 10.0  # how long it may take to exit after SIGTERM
    start_after: tuple[str, ...] = ()  # processes that must be up (have published health) before it starts
    nice: int = 0  # CPU priority below the others' by this much (`nice` increment)
    check: str = ""  # "module:function(car, config_path)" raising ConfigError: its start-up checks (check-config)


def driver_processes(config: CarConfig, config_path: str) -> list[ProcessSpec]:
    """One driver process per configured sensor, live. A sensor without a live driver has module "" (a point-cloud
    Lidar: its scans come only in logs, which the log player publishes under the driver's name)."""
    cfg = ("--config", config_path)
    s = config.sensors
    table = []
    for cam in s.cameras:
        module = "sim.camera_playback" if cam.backend == "sim" else "drivers.camera.camera_driver"
        table.append(ProcessSpec(camera_process(cam.name), module, cfg + ("--camera", cam.name), required=True,
                                 check="drivers.camera.camera_driver:check_config"))
    if s.lidar is not None and s.lidar.point_clouds:
        table.append(ProcessSpec("lidar", "", cfg, required=True))
    elif s.lidar is not None:  # Ouster packets have their own driver; the other vendors' share one
        module = "drivers.lidar.vendor_udp_driver" if s.lidar.vendor_packets else "drivers.lidar.udp_driver"
        table.append(ProcessSpec("lidar", module, cfg, required=True, check=f"{module}:check_config"))
    if s.gnss is not None:
        table.append(ProcessSpec("gnss", "drivers.gnss.serial_driver", cfg, required=True))
    if s.can is not None:
        table.append(ProcessSpec("can", "drivers.can.can_driver", cfg, required=True,
                                 check="drivers.can.can_driver:check_config"))
    return table


def playback_rate(text: str) -> float | None:
    """A replay's `--rate`: a speed factor (finite, > 0), or None for `max` (as fast as the consumers take it); any
    other text is a ValueError saying so. `roadlog replay` checks it before it starts any process, and the player
    reads it the same way."""
    if text == "max":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"--rate {text}: a playback speed factor > 0, or 'max'")
    return value


def process_table(
    config: CarConfig,
    config_path: str,
    mode: Mode,
    *,
    replay_logs: tuple[str, ...] = (),
    replay_rate: str = "1.0",
    record: bool = True,
    output_dir: str | None = None,
    map_stop_timeout_s: float = MAP_STOP_TIMEOUT_S,
) -> list[ProcessSpec]:
    """The processes of one daemon run. Live: one per driver; replay: the log player instead. A live run of a
    config with a sensor that has no live driver is a ConfigError (`roadlog run` and check-config exit 2)."""
    cfg = ("--config", config_path)
    out = ("--output-dir", output_dir) if output_dir else ()
    table: list[ProcessSpec] = []
    # what the log holds for viewing, made from the drivers' topics (a replay makes it again: the player plays only
    # the drivers' topics); only when there is a log
    viewers = (LIDAR_VIEW_PROCESS,) * (record and views_lidar(config)) + \
        (VEHICLE_POSE_PROCESS,) * (record and fuses_pose(config))
    if mode == "live":
        table += driver_processes(config, config_path)
        if any(not spec.module for spec in table):  # only a point-cloud Lidar has none
            raise ConfigError(f"{config_path}: sensors.lidar.model {POINT_CLOUD_LIDAR!r} has no live driver: its "
                              f"scans come decoded, only in logs (an imported dataset, another system's recording); "
                              f"use this config with `roadlog replay` or `roadlog reconstruct`")
    else:
        # the player starts once the recorder and the mapper listen: nothing is played before they subscribe
        consumers = ("recorder",) * record + ("mapper",) * config.mapper.enabled + viewers
        table.append(ProcessSpec("replay", "daemon.processes.replay", cfg + ("--rate", replay_rate) + replay_logs,
                                 restart_on_success=False, heartbeat_s=30.0, start_after=consumers))
    if record:
        anchors = ("--no-time-anchors",) if mode == "replay" else ()  # the player replays the recorded ones
        # replaying as fast as the consumers allow: the player waits for the recorder too, or it would overrun it
        lossless = ("--lossless",) if mode == "replay" and replay_rate == "max" else ()
        table.append(ProcessSpec("recorder", "daemon.processes.recorder", cfg + out + anchors + lossless,
                                 heartbeat_s=15.0, stop_timeout_s=30.0,
                                 check="daemon.processes.segment_files:check_output_dir"))
    # they start once the recorder is up (their products are for its log), so that their imports (the mapper's
    # modules: ~4 s of a core) do not slow the drivers' start; their first health may take as long
    viewing = {"nice": VIEWER_NICE, "start_after": ("recorder",), "heartbeat_s": 30.0}
    if LIDAR_VIEW_PROCESS in viewers:
        table.append(ProcessSpec(LIDAR_VIEW_PROCESS, "mapping.viewing.lidar_view", cfg,
                                 check="mapping.viewing.lidar_view:check_config", **viewing))
    if VEHICLE_POSE_PROCESS in viewers:
        table.append(ProcessSpec(VEHICLE_POSE_PROCESS, "mapping.viewing.vehicle_pose", cfg, **viewing))
    if config.mapper.enabled:
        # the log comes first: on a busy machine the drivers and the recorder get the CPU before the mapper
        # it plans its stop within its stop timeout; a replay's never skips a window (nothing is lost by waiting)
        lag = ("--stop-timeout-s", f"{map_stop_timeout_s:g}") + ("--no-skip",) * (mode == "replay")
        table.append(ProcessSpec("mapper", "mapping.live.mapping_worker", cfg + out + lag, heartbeat_s=120.0,
                                 stop_timeout_s=map_stop_timeout_s, restart_on_success=False, nice=MAPPER_NICE,
                                 check="mapping.inputs.drive_inputs:check_config"))
    table.append(ProcessSpec("status", "daemon.processes.status_server", cfg + out, heartbeat_s=0.0))
    return table


def required_drivers(config: CarConfig) -> list[str]:
    """The drivers whose health decides readiness, in live and replay runs alike (a replay stands in for them):
    the `required` driver processes, one per configured sensor (a point-cloud Lidar's too: a replay plays its
    topic)."""
    return sorted(spec.name for spec in driver_processes(config, "") if spec.required)


def played_topics(config: CarConfig) -> set[str]:
    """The topics the car's drivers publish (their health excepted) and the time anchors: what a replay plays, and so
    what the recorder's segment clock runs on, live and replay alike (the other topics are stamped by processes
    running now)."""
    drivers = set(required_drivers(config))
    return {name for name, t in topic_table(config).items()
            if t.source in drivers and name != health_topic(t.source)} | {TIME_ANCHOR}
