"""`roadlog check-config`: validate a car config and print it resolved (defaults filled in)."""

from __future__ import annotations

import argparse

from daemon.spine.config import config_to_yaml, load_config, reports_config_errors


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog check-config", description=__doc__)
    parser.add_argument("config", help="path of the car's YAML config")
    parser.add_argument("--quiet", action="store_true", help="print nothing when the config is valid")
    args = parser.parse_args(argv)
    config = load_config(args.config)
    if not args.quiet:
        print(config_to_yaml(config), end="")
    return 0
