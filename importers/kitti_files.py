"""Reading KITTI's files (calibration `key: numbers` text, UTC timestamp lists, numbered frames) and the car
config an imported KITTI log records (recorded cameras, the vehicle frame, the mapper's defaults)."""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.spine.config import CarConfig, ConfigError, parse_config
from daemon.spine.messages import CameraFrame
from daemon.spine.topics import camera_topic

# Camera axes (x right, y down, z forward) -> vehicle axes (x forward, y left, z up)
CAMERA_TO_FLU = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class DatasetError(ConfigError):
    """A dataset folder that cannot be imported: the message names the file and what is missing or wrong
    (exit 2, like a bad config: nothing was written)."""


def read_calibration(path: Path, unnamed: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """A KITTI calibration file as name -> numbers (lines `NAME: v v v ...`; text values such as calib_time
    are left out). Lines of bare numbers (some copies drop the names) take the names in `unnamed` in order."""
    if not path.is_file():
        raise DatasetError(f"{path}: calibration file missing")
    values, names = {}, iter(unnamed)
    for line in path.read_text().splitlines():
        name, sep, rest = line.partition(":")
        if not sep:
            name, rest = next(names, ""), line
        try:
            numbers = np.array([float(v) for v in rest.split()])
        except ValueError:
            continue
        if name.strip() and numbers.size:
            values[name.strip()] = numbers
    return values


def calibration_matrix(values: dict[str, np.ndarray], name: str, shape: tuple[int, int], path: Path) -> np.ndarray:
    if name not in values or values[name].size != shape[0] * shape[1]:
        raise DatasetError(f"{path}: no {name} with {shape[0] * shape[1]} numbers")
    return values[name].reshape(shape)


def rigid(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rotation, translation
    return t


def read_timestamps(path: Path) -> np.ndarray:
    """KITTI's `YYYY-MM-DD HH:MM:SS.fffffffff` lines (UTC) as int64 nanoseconds since the Unix epoch."""
    if not path.is_file():
        raise DatasetError(f"{path}: timestamps file missing")
    stamps = []
    for number, line in enumerate(path.read_text().split("\n"), 1):
        if not line.strip():
            continue
        try:
            whole, _, fraction = line.strip().partition(".")
            second = datetime.datetime.strptime(whole, "%Y-%m-%d %H:%M:%S").replace(tzinfo=datetime.UTC)
            stamps.append(int(second.timestamp()) * 1_000_000_000 + int(fraction.ljust(9, "0")[:9] or 0))
        except ValueError as exc:
            raise DatasetError(f"{path}:{number}: not a KITTI timestamp ({exc})") from None
    return np.array(stamps, np.int64)


def numbered_files(folder: Path, suffix: str) -> list[Path]:
    """The frames of a KITTI folder (NNNNNN.png, NNNNNNNNNN.txt, ...) in frame order."""
    files = sorted(folder.glob(f"*{suffix}"), key=lambda p: int(p.stem) if p.stem.isdigit() else -1)
    files = [p for p in files if p.stem.isdigit()]
    if not files:
        raise DatasetError(f"{folder}: no {suffix} frames")
    return files


def extrinsics(t_vehicle_sensor: np.ndarray) -> dict:
    """A 4x4 sensor -> vehicle transform as the config's extrinsics (translation, roll/pitch/yaw in degrees)."""
    yaw, pitch, roll = Rotation.from_matrix(t_vehicle_sensor[:3, :3]).as_euler("ZYX", degrees=True)
    return {"translation_m": [float(v) for v in t_vehicle_sensor[:3, 3]],
            "rotation_rpy_deg": [float(roll), float(pitch), float(yaw)]}


def recorded_camera(name: str, width: int, height: int, k: np.ndarray, t_vehicle_camera: np.ndarray,
                    rate_hz: float, encoding: str) -> dict:
    """The config of a camera whose frames exist only in the imported log (rectified: no distortion)."""
    return {"name": name, "backend": "recorded", "width": width, "height": height, "rate_hz": rate_hz,
            "intrinsics": {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2])},
            "extrinsics": extrinsics(t_vehicle_camera), "encoding": encoding}


def imported_car_config(name: str, cameras: list[dict], reference_height_m: float, source: Path,
                        **sensors) -> CarConfig:
    """The car config of an imported log: its recorded cameras and sensors, the vehicle reference point's height,
    every other section at its default (the mapper's too)."""
    data = {"vehicle": {"name": name, "reference_height_m": reference_height_m},
            "sensors": {"cameras": cameras, **sensors}}
    return parse_config(data, f"{source} (imported)")


def png_file_size(path: Path) -> tuple[int, int]:
    """(width, height) of a PNG file, from its first 24 bytes."""
    with open(path, "rb") as f:
        return png_size(f.read(24), path)


def png_size(data: bytes, path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        raise DatasetError(f"{path}: not a PNG file")
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def write_png_frames(writer, camera: str, images: list[Path], times_ns: list[int], size: tuple[int, int]) -> None:
    """Each PNG file as a frame of `camera` at its time, its bytes unchanged; one of another size is a DatasetError."""
    for i, (path, t) in enumerate(zip(images, times_ns, strict=True)):
        data = path.read_bytes()
        if png_size(data, path) != size:
            raise DatasetError(f"{path}: {png_size(data, path)} pixels, frame 0 has {size}")
        writer.write(camera_topic(camera), CameraFrame(seq=i, sensor_time_ns=int(t), host_mono_ns=int(t),
                                                       camera=camera, format="png", data=data))
