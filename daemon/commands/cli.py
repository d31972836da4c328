"""The `roadlog` command: one subcommand per job, each a module's `main(argv)`."""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> ("module[:function]" taking argv (default: main), one-line help): the only place a subcommand is declared.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("mapping.demo", "simulate a drive, run the daemon on it (replay, record, map), print what happened"),
    "check-config": ("daemon.commands.check_config", "validate a car config file and print the resolved config"),
    "log-info": ("daemon.commands.log_info", "summarise MCAP log files: topics, counts, time span, truncation"),
    "run": ("daemon.processes.daemon_main:run_main", "run the daemon on the car's live sensors (what systemd starts)"),
    "replay": ("daemon.processes.daemon_main:replay_main", "run the daemon with a log player instead of the drivers"),
    "simulate": ("sim.drive_log", "simulate a drive (city, ramp, night) into a log with ground truth"),
    "reconstruct": ("mapping.offline.reconstruct_command", "EMIE-MAP road map of drive logs, with the paper's metrics"),
    "import": ("importers.import_command", "a dataset (KITTI raw, KITTI odometry) as a roadlog log"),
    "status-server": ("daemon.processes.status_server",
                      "serve the status endpoint alone (the daemon starts it itself)"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="roadlog", description="ROS-free sensor logging and live road mapping.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in SUBCOMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        parser.error(f"unknown command {name!r} (choose from {', '.join(SUBCOMMANDS)})")
    module_name, _, function = SUBCOMMANDS[name][0].partition(":")
    entry = getattr(importlib.import_module(module_name), function or "main")
    return int(entry(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
