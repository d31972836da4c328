"""The shape `roadlog import` and `roadlog export` share: one subcommand per format, each format a module with
`add_arguments(parser)` and `run(args)`, named in a table and imported only when the command runs."""

from __future__ import annotations

import argparse
import importlib


def run_format_command(prog: str, description: str, formats: dict[str, tuple[str, str]],
                       argv: list[str] | None) -> int:
    """Parse `FORMAT ...` against `formats` (name -> (module, one-line help)) and run that format's module."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    subparsers = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for name, (module, help_text) in formats.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        handler = importlib.import_module(module)
        handler.add_arguments(sub)
        sub.set_defaults(run=handler.run)
    args = parser.parse_args(argv)
    return int(args.run(args))
