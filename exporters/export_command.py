"""`roadlog export FORMAT LOG... --out OUT`: roadlog logs in another system's format, for its tools. One exporter
module per format, each with `add_arguments(parser)` and `run(args)` (as `importers/import_command.py`)."""

from __future__ import annotations

import argparse
import importlib
import sys

# format -> (module, one-line help): the only place an export format is declared
FORMATS: dict[str, tuple[str, str]] = {
    "ros2": ("exporters.ros2_bag", "a ROS 2 bag: images, camera info, PointCloud2, NavSatFix, Imu, tf_static, pose"),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog export", description=__doc__.split("\n\n")[0])
    formats = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for name, (module, help_text) in FORMATS.items():
        sub = formats.add_parser(name, help=help_text, description=help_text)
        exporter = importlib.import_module(module)
        exporter.add_arguments(sub)
        sub.set_defaults(run=exporter.run)
    args = parser.parse_args(argv)
    return int(args.run(args))


if __name__ == "__main__":
    sys.exit(main())
