"""`roadlog check-config`: validate a car config, run every start-up check the daemon and its processes would make
(the process table names them: the rings against their messages and /dev/shm, Lidar metadata, DBC signals and units,
the segmentation model, ...), and print the config resolved (defaults filled in). Exit 2 when any check fails, with
one line per problem."""

from __future__ import annotations

import argparse
import importlib
import sys

from daemon.spine.config import (
    EXIT_CONFIG_ERROR,
    CarConfig,
    ConfigError,
    config_to_yaml,
    load_config,
    reports_config_errors,
)
from daemon.spine.process_logging import error_line
from daemon.spine.process_table import DAEMON_CHECK, process_table


def start_up_problems(config: CarConfig, config_path: str) -> list[str]:
    """What each process of a live run would refuse at start, one line each (empty: all would start)."""
    problems, checked = [], set()
    checks = [("bus", DAEMON_CHECK)] + [(s.name, s.check) for s in process_table(config, config_path, "live")]
    for name, check in checks:
        if not check or check in checked:  # one check may serve several processes (the cameras')
            continue
        checked.add(check)
        module, _, function = check.partition(":")
        try:
            getattr(importlib.import_module(module), function)(config, config_path)
        except ConfigError as exc:
            problems.append(f"{name}: {exc}")
    return problems


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog check-config", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="path of the car's YAML config")
    parser.add_argument("--quiet", action="store_true", help="print nothing when the config is valid")
    args = parser.parse_args(argv)
    config = load_config(args.config)
    problems = start_up_problems(config, args.config)
    for line in problems:
        print(error_line(line), file=sys.stderr)
    if problems:
        return EXIT_CONFIG_ERROR
    if not args.quiet:
        print(config_to_yaml(config), end="")
    return 0
