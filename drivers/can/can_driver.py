"""The CAN driver process: every raw frame to `can/frames`, decoded wheel speeds to `wheel_speeds`.

Works on any python-can interface the config names (socketcan on the car, virtual in tests,
udp_multicast from the simulator). Error frames are published (flagged) and counted; a bus-off error
frame is counted separately (socketcan's controller restarts itself after `restart-ms`). A CanError
or OSError from the bus (bus down, adapter unplugged) is counted and the bus is reopened with an
exponential backoff. Frames of the configured messages that cannot be decoded are counted as rejected.
A frame's sensor time is the interface's receive time stamp (wall clock on socketcan).
"""

from __future__ import annotations

import argparse
import dataclasses
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import can
from cantools.database import UnsupportedDatabaseFormatError

from daemon.spine.config import CanConfig, CarConfig, ConfigError, load_config, reports_config_errors, resolve_path
from daemon.spine.health import HealthCounters
from daemon.spine.messages import CanFrame
from daemon.spine.process_logging import setup_logging
from daemon.spine.stop_signals import set_on_signals
from daemon.spine.topics import CAN_FRAMES, WHEEL_SPEEDS, health_topic
from drivers.can.can_bus import open_can_bus
from drivers.can.wheel_speed_codec import (
    CanDecodeError,
    WheelSpeedDecoder,
    WheelSpeedLayoutError,
    load_dbc,
    wheel_speed_layout,
)

PROCESS = "can"
CAN_ERR_BUSOFF = 0x40  # error class bit in a socketcan error frame's id (linux/can/error.h)
BACKOFF_FIRST_S = 0.05
BACKOFF_MAX_S = 5.0

Publish = Callable[[str, object], None]


@dataclass
class CanDriverStats:
    """What the driver saw, beyond the generic health counters."""

    frames: int = 0
    error_frames: int = 0
    bus_off: int = 0
    bus_errors: int = 0  # CanError/OSError raised by the bus (open, recv)
    reopens: int = 0
    undecodable: int = 0
    wheel_speeds: int = 0

    def summary(self) -> str:
        return " ".join(f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self))


def can_frame(msg: can.Message) -> CanFrame:
    return CanFrame(
        sensor_time_ns=round(msg.timestamp * 1e9),
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_error_frame=msg.is_error_frame,
        is_remote_frame=msg.is_remote_frame,
        channel=str(msg.channel) if msg.channel is not None else "",
        data=bytes(msg.data),
    )


def _publish_health(publish: Publish, health: HealthCounters, stats: CanDriverStats) -> None:
    snap = health.snapshot()
    detail = stats.summary() + (f"; last error: {health.last_error}" if health.last_error else "")
    publish(health_topic(PROCESS), dataclasses.replace(snap, detail=detail))


def _close(bus: can.BusABC, health: HealthCounters, stats: CanDriverStats) -> None:
    try:
        bus.shutdown()
    except (can.CanError, OSError) as exc:
        stats.bus_errors += 1
        health.count_error(f"closing the bus: {exc}")


def _handle_frame(msg: can.Message, decoder: WheelSpeedDecoder, publish: Publish, health: HealthCounters,
                  stats: CanDriverStats) -> None:
    stats.frames += 1
    health.received += 1
    frame = can_frame(msg)
    publish(CAN_FRAMES, frame)
    health.count_published()
    if msg.is_error_frame:
        stats.error_frames += 1
        if msg.arbitration_id & CAN_ERR_BUSOFF:
            stats.bus_off += 1
            health.count_error(f"bus-off (error frame 0x{msg.arbitration_id:x})")
        else:
            health.count_error(f"error frame 0x{msg.arbitration_id:x} data {frame.data.hex()}")
        return
    if msg.is_remote_frame:
        return
    try:
        speeds = decoder.decode(msg.arbitration_id, msg.is_extended_id, frame.data, frame.sensor_time_ns)
    except CanDecodeError as exc:
        stats.undecodable += 1
        health.count_rejected(str(exc))
        return
    health.sequence_gaps = decoder.counter_gaps
    if speeds is not None:
        publish(WHEEL_SPEEDS, speeds)
        health.count_published()
        stats.wheel_speeds += 1


def run_can_driver(
    config: CanConfig,
    dbc_path: str | Path,
    publish: Publish,
    stop: threading.Event,
    health: HealthCounters,
    *,
    open_bus: Callable[..., can.BusABC] = open_can_bus,
    bus_kwargs: Mapping[str, object] | None = None,
    health_period_s: float = 1.0,
    recv_timeout_s: float = 0.1,
) -> CanDriverStats:
    """Receive, publish and decode frames until `stop` is set; health goes out every `health_period_s`."""
    decoder = WheelSpeedDecoder(wheel_speed_layout(load_dbc(dbc_path), config.signals))
    stats = CanDriverStats()
    bus: can.BusABC | None = None
    backoff_s = BACKOFF_FIRST_S
    next_health = time.monotonic() + health_period_s
    try:
        while not stop.is_set():
            now = time.monotonic()
            if now >= next_health:
                _publish_health(publish, health, stats)
                next_health = now + health_period_s
            if bus is None:
                try:
                    bus = open_bus(config, **(bus_kwargs or {}))
                except (can.CanError, OSError) as exc:
                    stats.bus_errors += 1
                    health.count_error(f"opening {config.interface}:{config.channel}: {exc}")
                    stop.wait(backoff_s)
                    backoff_s = min(2 * backoff_s, BACKOFF_MAX_S)
                    continue
            try:
                msg = bus.recv(timeout=recv_timeout_s)
            except (can.CanError, OSError) as exc:
                stats.bus_errors += 1
                stats.reopens += 1
                health.count_error(f"bus error on {config.interface}:{config.channel}: {exc}")
                _close(bus, health, stats)
                bus = None
                stop.wait(backoff_s)
                backoff_s = min(2 * backoff_s, BACKOFF_MAX_S)
                continue
            if msg is None:
                continue
            backoff_s = BACKOFF_FIRST_S
            _handle_frame(msg, decoder, publish, health, stats)
    finally:
        if bus is not None:
            _close(bus, health, stats)
    _publish_health(publish, health, stats)
    return stats


def check_config(car: CarConfig, config_path: str | Path,
                 dbc: str | Path | None = None) -> tuple[Path, float | None]:
    """What the driver checks before it starts (also run by `roadlog check-config`): the DBC loads and holds the
    configured wheel-speed signals in a usable unit. Returns the DBC's path and the wheel message's cycle (ms)."""
    if car.sensors.can is None:
        raise ConfigError(f"{config_path}: has no sensors.can section")
    dbc_path = Path(dbc) if dbc else resolve_path(config_path, car.sensors.can.dbc_file)
    try:
        cycle_ms = wheel_speed_layout(load_dbc(dbc_path), car.sensors.can.signals).wheel_message.cycle_time
    except (OSError, UnsupportedDatabaseFormatError, WheelSpeedLayoutError) as exc:
        raise ConfigError(f"{config_path}: sensors.can with DBC {str(dbc_path)!r}: {exc}") from None
    return dbc_path, cycle_ms


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="roadlog CAN driver: raw frames and wheel speeds onto the bus")
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--interface", help="override sensors.can.interface (python-can interface name)")
    parser.add_argument("--channel", help="override sensors.can.channel")
    parser.add_argument("--dbc", help="override sensors.can.dbc_file")
    args = parser.parse_args(argv)
    setup_logging(PROCESS)

    from daemon.bus.pubsub import open_publisher

    car = load_config(args.config)
    dbc_path, cycle_ms = check_config(car, args.config, args.dbc)
    overrides = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v}
    config = car.sensors.can.model_copy(update=overrides)
    publishers = {topic: open_publisher(car, topic) for topic in (CAN_FRAMES, WHEEL_SPEEDS, health_topic(PROCESS))}
    health = HealthCounters(PROCESS, expected_rate_hz=1000.0 / cycle_ms if cycle_ms else 0.0)
    stop = threading.Event()
    set_on_signals(stop)
    stats = run_can_driver(config, dbc_path, lambda topic, m: publishers[topic].publish(m), stop, health)
    print(f"can driver stopped: {stats.summary()}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
