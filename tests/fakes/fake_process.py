"""A stand-in daemon process for supervisor tests: publishes health, then behaves as told."""

import argparse
import signal
import sys
import time

from daemon.bus.pubsub import open_publisher
from daemon.spine.config import load_config
from daemon.spine.health import HealthCounters
from daemon.spine.process_logging import setup_logging
from daemon.spine.topics import health_topic


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--config", required=True)
    parser.add_argument("--name", required=True)
    parser.add_argument("--behaviour", default="ok", choices=["ok", "crash", "hang", "done", "slow-stop", "bad-config",
                                                             "slow-start"])
    parser.add_argument("--after", type=float, default=1.0)
    parser.add_argument("--marker", default="")
    args = parser.parse_args()
    setup_logging(args.name)  # as every real process: SIGUSR1 dumps its stacks
    config = load_config(args.config)
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(1))
    pub = open_publisher(config, health_topic(args.name))
    health = HealthCounters(args.name, expected_rate_hz=10.0)
    start = time.monotonic()
    while not stopping:
        elapsed = time.monotonic() - start
        if elapsed > args.after:
            if args.behaviour == "crash":
                return 3
            if args.behaviour == "done":
                return 0
            if args.behaviour == "bad-config":
                return 2
            if args.behaviour == "hang":
                time.sleep(3600)
        health.count_published(10)
        msg = health.snapshot()
        if args.behaviour == "slow-start" and elapsed <= args.after:
            msg.state = "starting"  # alive, loading (the mapper before torch)
        pub.publish(msg)
        time.sleep(0.1)
    if args.behaviour == "slow-stop":
        time.sleep(3600)
    if args.marker:
        with open(args.marker, "a") as f:
            f.write(f"{args.name} stopped cleanly\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
