"""The GNSS/IMU driver process: reads the receiver's serial port, frames, decodes, publishes, counts.

A read error or a vanished port (cable unplugged) closes the port; it is reopened with exponential
backoff and the driver carries on. Health goes out once a second, also while the port is down.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import serial

from daemon.bus.pubsub import open_publisher
from daemon.spine import topics
from daemon.spine.config import ConfigError, GnssConfig, load_config, reports_config_errors
from daemon.spine.health import HealthCounters
from daemon.spine.process_logging import setup_logging
from daemon.spine.stop_signals import set_on_signals
from drivers.gnss.gnss_messages import GnssDecoder
from drivers.gnss.stream_framer import StreamFramer

PROCESS = "gnss"
READ_TIMEOUT_S = 0.1
REOPEN_BACKOFF_S = (0.1, 2.0)  # first wait, longest wait
HEALTH_PERIOD_S = 1.0
log = logging.getLogger(__name__)

Publish = Callable[[str, object], None]


@dataclass(frozen=True)
class GnssDriverStats:
    """What one driver run saw, by kind: framer rejections and decoder outcomes."""

    framer: dict[str, int]
    decoder: dict[str, int]
    frame_bytes: int
    skipped_bytes: int


def health_detail(port: str, port_state: str, framer: StreamFramer, decoder: GnssDecoder,
                  last_error: str) -> str:
    """One line: port state, rejections by kind, decoder outcomes, the last error."""
    rejected = ", ".join(f"{k}={v}" for k, v in sorted(framer.counts.items()))
    decoded = ", ".join(f"{k}={v}" for k, v in sorted(decoder.counts.items()))
    return (f"port {port} {port_state}; framer: {rejected or 'clean'}; decoder: {decoded or '-'}; "
            f"last error: {last_error or '-'}")


class _Loop:
    """The state shared by the read loop and the health ticker of one driver run."""

    def __init__(self, config: GnssConfig, port: str, publish: Publish, health: HealthCounters) -> None:
        self.port = port
        self.publish = publish
        self.health = health
        self.framer = StreamFramer(health)
        self.decoder = GnssDecoder(config.protocol, health)
        self.port_state = "closed"  # open | closed | stopped
        self.next_health_ns = time.monotonic_ns()

    def emit(self, messages: list) -> None:
        for message in messages:
            topic = topics.GNSS_TOPIC_BY_TYPE[type(message)]
            try:
                self.publish(topic, message)
            except Exception as exc:  # a bus failure must not stop the sensor; it is counted and reported
                self.health.dropped += 1
                self.health.count_error(f"publish {topic}: {exc!r}")
                continue
            self.health.count_published()

    def take(self, data: bytes, arrival_ns: int) -> None:
        for frame in self.framer.feed(data):
            self.health.received += 1
            self.emit(self.decoder.decode(frame, arrival_ns))

    def end_of_stream(self) -> None:
        """The port closed: what is left in the framer is truncated; publish what was waiting."""
        arrival_ns = time.monotonic_ns()
        for frame in self.framer.flush():
            self.health.received += 1
            self.emit(self.decoder.decode(frame, arrival_ns))
        self.emit(self.decoder.flush())

    def tick_health(self) -> None:
        now = time.monotonic_ns()
        if now < self.next_health_ns:
            return
        self.next_health_ns = now + int(HEALTH_PERIOD_S * 1e9)
        snapshot = self.health.snapshot(now)
        detail = health_detail(self.port, self.port_state, self.framer, self.decoder, self.health.last_error)
        state = "error" if self.port_state == "closed" else snapshot.state
        try:
            message = replace(snapshot, state=state, detail=detail)
            self.publish(topics.health_topic(PROCESS), message)
        except Exception as exc:  # see emit()
            self.health.count_error(f"publish health: {exc!r}")

    def wait(self, stop: threading.Event, seconds: float) -> None:
        """Sleep (waking for health ticks) until `seconds` pass or stop is set."""
        deadline = time.monotonic() + seconds
        while not stop.is_set():
            self.tick_health()
            left = deadline - time.monotonic()
            if left <= 0:
                return
            stop.wait(min(left, HEALTH_PERIOD_S))


def run_gnss_driver(
    config: GnssConfig,
    port: str,
    publish: Publish,
    stop: threading.Event,
    health: HealthCounters,
    backoff_s: tuple[float, float] = REOPEN_BACKOFF_S,
) -> GnssDriverStats:
    """Read `port` until `stop` is set; publish fixes on topics.GNSS_FIX, velocities on topics.GNSS_VELOCITY, IMU
    samples on topics.IMU and health on health_topic("gnss"). Never raises for port trouble: it is counted and the
    port reopened."""
    loop = _Loop(config, port, publish, health)
    backoff = backoff_s[0]
    while not stop.is_set():
        try:
            link = serial.Serial(port, baudrate=config.baud, timeout=READ_TIMEOUT_S)
        except (serial.SerialException, OSError, ValueError) as exc:
            health.count_error(f"open {port}: {exc}")
            loop.wait(stop, backoff)
            backoff = min(2 * backoff, backoff_s[1])
            continue
        loop.port_state = "open"
        log.info("opened %s at %d baud", port, config.baud)
        try:
            while not stop.is_set():
                data = link.read(link.in_waiting or 1)
                arrival_ns = time.monotonic_ns()
                if data:
                    loop.take(data, arrival_ns)
                    backoff = backoff_s[0]
                loop.tick_health()
        except (serial.SerialException, OSError) as exc:  # unplugged: the port reports EIO or vanishes
            health.count_error(f"read {port}: {exc}")
            log.warning("lost %s: %s", port, exc)
        finally:
            loop.port_state = "closed"
            link.close()
            loop.end_of_stream()
        if not stop.is_set():
            loop.wait(stop, backoff)
            backoff = min(2 * backoff, backoff_s[1])
    loop.port_state = "stopped"
    loop.next_health_ns = 0
    loop.tick_health()
    framer, decoder = loop.framer, loop.decoder
    return GnssDriverStats(dict(framer.counts), dict(decoder.counts), framer.frame_bytes,
                           framer.skipped_bytes)


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="roadlog GNSS/IMU serial driver")
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--port", help="serial port, overriding sensors.gnss.port")
    args = parser.parse_args(argv)
    setup_logging("gnss")
    config = load_config(args.config)
    gnss = config.sensors.gnss
    if gnss is None:
        raise ConfigError(f"{args.config}: sensors.gnss is not configured")
    names = (*topics.GNSS_TOPIC_BY_TYPE.values(), topics.health_topic(PROCESS))
    publishers = {name: open_publisher(config, name) for name in names}
    stop = threading.Event()
    set_on_signals(stop)
    health = HealthCounters(process=PROCESS, expected_rate_hz=gnss.rate_hz)
    port = args.port or gnss.port
    try:
        stats = run_gnss_driver(gnss, port, lambda topic, msg: publishers[topic].publish(msg), stop, health)
    finally:
        for publisher in publishers.values():
            publisher.close()
    log.info("gnss driver stopped: published %d, rejected %d, errors %d; framer %s; decoder %s",
             health.published, health.rejected, health.errors, stats.framer, stats.decoder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
