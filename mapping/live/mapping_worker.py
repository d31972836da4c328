"""The live mapping worker's process: `python -m mapping.live.mapping_worker --config PATH [--output-dir DIR]
[--stop-timeout-s S] [--no-skip]`.

Its first health message goes out before it imports torch and the fits (seconds of a core, minutes at a low CPU
priority on a loaded machine): state `starting`, once a second, until the worker's own health takes over
(`mapping.live.worker_loop`, which says what the worker does). The supervisor counts a `starting` health as
alive but not as up: a replay that waits for the mapper waits until it listens. `--stop-timeout-s` is the time
the supervisor gives it after SIGTERM (the process table passes it); `--no-skip` keeps every window however far
behind it is (a replay: nothing is lost by waiting for it).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading

from daemon.bus import pubsub
from daemon.spine.config import CarConfig, load_config, reports_config_errors
from daemon.spine.health import HealthCounters
from daemon.spine.mapper_config import DEVICES
from daemon.spine.process_logging import setup_logging
from daemon.spine.process_table import MAP_STOP_TIMEOUT_S
from daemon.spine.stop_signals import on_signals
from daemon.spine.topics import health_topic
from mapping.live.lag_policy import StopRequest

PROCESS = "mapper"
STARTING = "starting"


def publish_starting(config: CarConfig, done: threading.Event) -> threading.Thread:
    """A `starting` health at once and then every second until `done` (the worker's own health takes over)."""
    pub = pubsub.open_publisher(config, health_topic(PROCESS))
    health = HealthCounters(PROCESS)

    def starting() -> None:
        while True:
            msg = health.snapshot()
            msg.state = STARTING
            msg.detail = json.dumps({"starting": "loading the mapper (torch, the fits)"})
            pub.publish(msg)
            if done.wait(1.0):
                pub.close()
                return

    thread = threading.Thread(target=starting, name="mapper-starting", daemon=True)
    thread.start()
    return thread


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapping_worker", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--output-dir", help="data folder (default: recorder.output_dir of the config)")
    parser.add_argument("--device", choices=DEVICES, help="torch device of the fits (default: mapper.device)")
    parser.add_argument("--stop-timeout-s", type=float, default=MAP_STOP_TIMEOUT_S,
                        help=f"seconds it may take after SIGTERM (default {MAP_STOP_TIMEOUT_S:g}; 0: no limit)")
    parser.add_argument("--no-skip", action="store_true", help="never skip windows, however far behind")
    args = parser.parse_args(argv)
    setup_logging(PROCESS)
    stop = StopRequest()
    on_signals(stop)
    config = load_config(args.config)
    started = threading.Event()
    starting = publish_starting(config, started)
    try:
        from mapping.live.worker_loop import MappingWorker  # torch and the fits: after the first health
        from mapping.method.compute_device import with_device

        worker = MappingWorker(with_device(config, args.device), args.config, args.output_dir,
                               skips=not args.no_skip)  # a ConfigError here: exit 2, not retried
    finally:
        started.set()
        starting.join()
    return worker.run(stop, args.stop_timeout_s or None)


if __name__ == "__main__":
    sys.exit(main())
