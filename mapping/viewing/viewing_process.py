"""The shape the viewing processes share (`lidar_view`, `vehicle_pose`): subscribe to the bus topics they derive
their output from (retrying until each ring exists), read what arrives in bursts, hand it to the process's step,
publish what the step gives and a health report once a second; at the stop, what the rings still hold and a last
step; and their `main`: arguments, logging, the "nothing to do" configuration error, SIGTERM/SIGINT."""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from collections.abc import Callable

from daemon.bus import pubsub
from daemon.spine.config import CarConfig, ConfigError, load_config
from daemon.spine.health import HealthCounters
from daemon.spine.process_logging import setup_logging
from daemon.spine.stop_signals import set_on_signals
from daemon.spine.topics import health_topic, topic_table

HEALTH_PERIOD_S = 1.0
SUBSCRIBE_RETRY_S = 0.5
IDLE_SLEEP_S = 0.005
READ_BURST = 256  # most messages taken from one ring before the next ring's turn
log = logging.getLogger(__name__)

# what was read this round ((topic, message) in arrival order per ring), and whether the data has ended (the stop)
# -> the messages to publish
Step = Callable[[list[tuple[str, object]], bool], list]
# -> (errors, the health report's detail)
Report = Callable[[], tuple[int, dict]]


def serve(config: CarConfig, process: str, inputs: list[str], output: str, step: Step, report: Report,
          stop: threading.Event) -> None:
    """Run a viewing process until `stop` is set (see the module docstring)."""
    wanted = [t for t in inputs if t in topic_table(config)]
    health = HealthCounters(process)
    out = pubsub.open_publisher(config, output)
    health_pub = pubsub.open_publisher(config, health_topic(process))
    subs: dict[str, pubsub.Subscriber] = {}

    def publish(messages: list) -> None:
        for msg in messages:
            out.publish(msg)
            health.count_published()

    last_try = last_health = 0.0
    try:
        while not stop.is_set():
            now = time.monotonic()
            if len(subs) < len(wanted) and now - last_try >= SUBSCRIBE_RETRY_S:
                last_try = now
                for topic in wanted:
                    if topic not in subs:
                        try:
                            subs[topic] = pubsub.open_subscriber(config, topic, start="oldest")
                        except FileNotFoundError:
                            pass
            if now - last_health >= HEALTH_PERIOD_S:
                last_health = now
                msg = health.snapshot()
                msg.dropped = sum(s.lost for s in subs.values())
                msg.errors, detail = report()
                msg.detail = json.dumps(detail)
                health_pub.publish(msg)
            read = [(topic, msg) for topic, sub in subs.items() for msg in _burst(sub)]
            health.received += len(read)
            publish(step(read, False))
            if not read:
                stop.wait(IDLE_SLEEP_S)
        # stopped (the supervisor stops these after the drivers, before the recorder): what the rings still hold
        read = [(topic, msg) for topic, sub in subs.items() for msg in _burst(sub, limit=None)]
        health.received += len(read)
        publish(step(read, True))
    finally:
        for closing in (*subs.values(), out, health_pub):
            closing.close()


def _burst(sub: pubsub.Subscriber, limit: int | None = READ_BURST) -> list:
    got = []
    while limit is None or len(got) < limit:
        msg = sub.read(timeout_s=0, copy=True)
        if msg is None:
            break
        got.append(msg)
    return got


def viewing_main(argv: list[str] | None, process: str, prog: str, description: str,
                 has_work: Callable[[CarConfig], bool], nothing_to_do: str,
                 run: Callable[[CarConfig, str, threading.Event], str]) -> int:
    """A viewing process's `main`: `--config PATH`; a ConfigError naming `nothing_to_do` when the car gives it no
    work; `run` until SIGTERM/SIGINT, then its summary line in the log."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--config", required=True, help="car config YAML")
    args = parser.parse_args(argv)
    setup_logging(process)
    config = load_config(args.config)
    if not has_work(config):
        raise ConfigError(f"{args.config}: {nothing_to_do}")
    stop = threading.Event()
    set_on_signals(stop)
    log.info("%s stopped: %s", process, run(config, args.config, stop))
    return 0
