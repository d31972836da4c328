"""`roadlog import FORMAT SOURCE --out LOG.mcap`: a dataset or another system's recording as a roadlog log (with
its car config recorded, so `roadlog reconstruct LOG` and `roadlog log-info LOG` need nothing else). One importer
module per format, each with `add_arguments(parser)` and `run(args)` (daemon/commands/format_subcommands.py)."""

from __future__ import annotations

import sys

from daemon.commands.format_subcommands import run_format_command

# format -> (module, one-line help): the only place an import format is declared
FORMATS: dict[str, tuple[str, str]] = {
    "kitti-raw": ("importers.kitti_raw", "a KITTI raw drive: image_02, oxts, calib_*.txt (velodyne_points)"),
    "kitti-odometry": ("importers.kitti_odometry", "a KITTI odometry sequence: image_0, poses.txt, calib.txt"),
    "ros2": ("importers.ros2_bag", "a ROS 2 bag: images, camera info, NavSatFix, Imu, Odometry, tf"),
}


def main(argv: list[str] | None = None) -> int:
    return run_format_command("roadlog import", __doc__.split("\n\n")[0], FORMATS, argv)


if __name__ == "__main__":
    sys.exit(main())
