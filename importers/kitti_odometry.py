"""`roadlog import kitti-odometry DIR --out LOG.mcap`: a KITTI odometry sequence (greyscale left camera `image_0`,
`poses.txt`, `calib.txt`) as a roadlog log that `roadlog reconstruct LOG` maps with nothing else.

KITTI's poses are camera 0 -> world, with world = camera 0 at the first frame (x right, y down, z forward). The log's
vehicle frame is camera 0 with the car's axes (x forward, y left, z up) and sits `--camera-height-m` (KITTI: 1.65 m)
above the road; its `pose` topic is the vehicle in the first vehicle frame (x along the starting heading, z up;
not geo-referenced). Frames carry their PNG bytes unchanged; the sequence has no times file, so frame i is at
i / `--rate-hz` (KITTI odometry: 10 Hz) on one clock for every topic.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from daemon.spine.config import reports_config_errors
from daemon.spine.topics import POSE
from importers.imported_log import ImportSummary, imported_log, vehicle_pose
from importers.kitti_files import (
    CAMERA_TO_FLU,
    DatasetError,
    calibration_matrix,
    imported_car_config,
    numbered_files,
    png_file_size,
    read_calibration,
    recorded_camera,
    rigid,
    write_png_frames,
)

CAMERA = "image_0"
KITTI_ODOMETRY_CALIBRATION = ("P0", "P1", "P2", "P3", "Tr")  # calib.txt's rows, in KITTI's order
CLOCK_START_NS = 1_000_000_000  # frame 0's time on the log's clock (any positive start would do)


def read_poses(path: Path) -> np.ndarray:
    """poses.txt: one row-major 3x4 camera -> world matrix per line, as (N, 4, 4)."""
    if not path.is_file():
        raise DatasetError(f"{path}: poses file missing")
    try:
        rows = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"{path}: not 12 numbers per line ({exc})") from None
    if rows.shape[1] != 12:
        raise DatasetError(f"{path}: {rows.shape[1]} numbers per line, expected 12 (a 3x4 matrix)")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows.reshape(-1, 3, 4)
    return poses


def vehicle_poses(camera_poses: np.ndarray) -> np.ndarray:
    """Camera 0 -> world(camera 0 at frame 0) as vehicle -> first vehicle frame (both with x forward, z up)."""
    axes = rigid(CAMERA_TO_FLU, np.zeros(3))
    return axes @ camera_poses @ axes.T


def import_odometry(folder: Path, out: Path, *, camera_height_m: float = 1.65, rate_hz: float = 10.0
                    ) -> ImportSummary:
    started = time.perf_counter()
    calib_path = folder / "calib.txt"
    p0 = calibration_matrix(read_calibration(calib_path, unnamed=KITTI_ODOMETRY_CALIBRATION), "P0", (3, 4), calib_path)
    images = numbered_files(folder / CAMERA, ".png")
    poses = vehicle_poses(read_poses(folder / "poses.txt"))
    if len(poses) < len(images):
        raise DatasetError(f"{folder / 'poses.txt'}: {len(poses)} poses for {len(images)} images of {CAMERA}")
    width, height = png_file_size(images[0])
    camera = recorded_camera(CAMERA, width, height, p0[:, :3], rigid(CAMERA_TO_FLU, np.zeros(3)), rate_hz, "png")
    config = imported_car_config("kitti-odometry", [camera], camera_height_m, folder)
    times = CLOCK_START_NS + np.round(np.arange(len(images)) / rate_hz * 1e9).astype(np.int64)
    metadata = {"source": f"KITTI odometry {folder.resolve()}",
                "import": json.dumps({"camera_height_m": camera_height_m, "rate_hz": rate_hz})}
    with imported_log(out, config, metadata) as writer:
        for i, (pose, t) in enumerate(zip(poses, times.tolist(), strict=False)):  # poses.txt may run on
            writer.write(POSE, vehicle_pose(pose, t, t, "map", seq=i))
        write_png_frames(writer, CAMERA, images, times.tolist(), (width, height))
        counts = dict(writer.counts)
    return ImportSummary(out, counts, float(times[-1] - times[0]) / 1e9, time.perf_counter() - started)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", type=Path, help="the sequence folder (image_0/, poses.txt, calib.txt)")
    parser.add_argument("--out", required=True, type=Path, help="the MCAP log to write")
    parser.add_argument("--camera-height-m", type=float, default=1.65, help="camera 0 above the road (m)")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="the camera's frame rate")


@reports_config_errors
def run(args: argparse.Namespace) -> int:
    summary = import_odometry(args.folder, args.out, camera_height_m=args.camera_height_m, rate_hz=args.rate_hz)
    print(summary.as_json())
    return 0
