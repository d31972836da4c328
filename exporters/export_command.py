"""`roadlog export FORMAT LOG... --out OUT`: roadlog logs in another system's format, for its tools. One exporter
module per format, each with `add_arguments(parser)` and `run(args)` (daemon/commands/format_subcommands.py)."""

from __future__ import annotations

import sys

from daemon.commands.format_subcommands import run_format_command

# format -> (module, one-line help): the only place an export format is declared
FORMATS: dict[str, tuple[str, str]] = {
    "ros2": ("exporters.ros2_bag", "a ROS 2 bag: images, camera info, PointCloud2, NavSatFix, Imu, tf_static, pose"),
}


def main(argv: list[str] | None = None) -> int:
    return run_format_command("roadlog export", __doc__.split("\n\n")[0], FORMATS, argv)


if __name__ == "__main__":
    sys.exit(main())
