"""The `roadlog` command: one subcommand per job, each a module's `main(argv)`."""

from __future__ import annotations

import argparse
import importlib
import sys

from daemon.log_format.metadata_records import SOFTWARE_VERSION
from daemon.spine.config import EXIT_CONFIG_ERROR, ConfigError
from daemon.spine.process_logging import error_line

# name -> ("module[:function]" taking argv (default: main), one-line help): the only place a subcommand is declared.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("mapping.demo", "simulate a drive, run the daemon on it (replay, record, map), print what happened"),
    "check-config": ("daemon.commands.check_config", "validate a car config file and print the resolved config"),
    "log-info": ("daemon.commands.log_info", "summarise MCAP log files: topics, counts, time span, truncation"),
    "run": ("daemon.processes.daemon_main:run_main", "run the daemon on the car's live sensors (what systemd starts)"),
    "replay": ("daemon.processes.daemon_main:replay_main", "run the daemon with a log player instead of the drivers"),
    "simulate": ("sim.drive_log", "simulate a drive (city, ramp, night) into a log with ground truth"),
    "reconstruct": ("mapping.offline.reconstruct_command", "EMIE-MAP road map of drive logs, with the paper's metrics"),
    "fleet": ("mapping.fleet.fleet_command", "`fleet reconstruct`: many drives mapped on Ray into one merged map"),
    "import": ("importers.import_command", "a dataset (KITTI raw, KITTI odometry) as a roadlog log"),
    "export": ("exporters.export_command", "roadlog logs as another system's recording (a ROS 2 bag)"),
    "status-server": ("daemon.processes.status_server",
                      "serve the status endpoint alone (the daemon starts it itself)"),
}


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand. A bad path or input it meets (a ConfigError, or a file it cannot open) is one
    `error: ...` line on stderr and exit status 2, never a traceback."""
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="roadlog", description="ROS-free sensor logging and live road mapping.")
    parser.add_argument("--version", action="version", version=SOFTWARE_VERSION)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in SUBCOMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    if not argv or argv[0] in ("-h", "--help", "--version"):
        parser.parse_args(argv[:1])  # prints the version and exits
        parser.print_help()
        return 0
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        parser.error(f"unknown command {name!r} (choose from {', '.join(SUBCOMMANDS)})")
    module_name, _, function = SUBCOMMANDS[name][0].partition(":")
    entry = getattr(importlib.import_module(module_name), function or "main")
    try:
        return int(entry(rest) or 0)
    except ConfigError as exc:  # a command whose main() does not report its own
        print(error_line(str(exc)), file=sys.stderr)
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError) as exc:
        print(error_line(f"{exc.filename}: {exc.strerror}" if exc.filename else str(exc)), file=sys.stderr)
    return EXIT_CONFIG_ERROR


if __name__ == "__main__":
    sys.exit(main())
