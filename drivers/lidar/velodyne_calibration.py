"""Velodyne per-laser calibration: read the calibration YAML (the ROS velodyne_pointcloud layout that
Nebula and velodyne-decoder use) into one typed dataclass of per-laser arrays, angles in radians and
distances in metres as the file gives them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

# Per-laser keys, their defaults when a file leaves them out (as velodyne_pointcloud reads them).
_LASER_KEYS_WITH_DEFAULTS: dict[str, float | None] = {
    "rot_correction": None,
    "vert_correction": None,
    "dist_correction": 0.0,
    "dist_correction_x": 0.0,
    "dist_correction_y": 0.0,
    "vert_offset_correction": 0.0,
    "horiz_offset_correction": 0.0,
    "focal_distance": 0.0,
    "focal_slope": 0.0,
    "min_intensity": 0.0,
    "max_intensity": 255.0,
}


@dataclass
class VelodyneCalibration:
    """Corrections of the L lasers of one sensor, indexed by laser id (the channel in the packet)."""

    source: str  # the file it was read from, for messages
    num_lasers: int
    distance_resolution_m: float  # metres per range unit of the packet
    rot_correction_rad: np.ndarray  # (L,) float64, azimuth offset of each laser
    vert_correction_rad: np.ndarray  # (L,) float64, elevation of each laser
    dist_correction_m: np.ndarray  # (L,) float64
    dist_correction_x_m: np.ndarray  # (L,) float64, two-point correction (HDL-64E)
    dist_correction_y_m: np.ndarray  # (L,) float64
    vert_offset_m: np.ndarray  # (L,) float64
    horiz_offset_m: np.ndarray  # (L,) float64
    focal_distance: np.ndarray  # (L,) float64, intensity correction (HDL-64E)
    focal_slope: np.ndarray  # (L,) float64
    min_intensity: np.ndarray  # (L,) float64
    max_intensity: np.ndarray  # (L,) float64
    ring: np.ndarray  # (L,) uint16, rank of the laser by elevation, 0 = lowest

    @property
    def two_point_correction(self) -> bool:
        """Whether the distance-dependent x/y corrections change anything."""
        return bool(np.any(self.dist_correction_x_m != self.dist_correction_m)) or bool(
            np.any(self.dist_correction_y_m != self.dist_correction_m)
        )


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: expected a number, got {value!r}")
    return float(value)


def parse_velodyne_calibration(doc: Any, source: str = "<calibration>") -> VelodyneCalibration:
    """The calibration of a parsed YAML document; ValueError naming `source` and the key when bad."""
    if not isinstance(doc, dict):
        raise ValueError(f"{source}: expected a mapping at the top level")
    for key in ("lasers", "num_lasers"):
        if key not in doc:
            raise ValueError(f"{source}: missing key {key!r}")
    num_lasers = int(_number(doc["num_lasers"], f"{source}: num_lasers"))
    lasers = doc["lasers"]
    if not isinstance(lasers, list) or len(lasers) != num_lasers:
        got = len(lasers) if isinstance(lasers, list) else type(lasers).__name__
        raise ValueError(f"{source}: 'lasers' must list num_lasers={num_lasers} lasers, got {got}")
    resolution = _number(doc.get("distance_resolution", 0.002), f"{source}: distance_resolution")
    if resolution <= 0:
        raise ValueError(f"{source}: distance_resolution must be > 0, got {resolution}")

    values = {key: np.full(num_lasers, np.nan) for key in _LASER_KEYS_WITH_DEFAULTS}
    seen = np.zeros(num_lasers, dtype=bool)
    for i, laser in enumerate(lasers):
        if not isinstance(laser, dict) or "laser_id" not in laser:
            raise ValueError(f"{source}: lasers[{i}] has no 'laser_id'")
        laser_id = int(_number(laser["laser_id"], f"{source}: lasers[{i}].laser_id"))
        if not 0 <= laser_id < num_lasers or seen[laser_id]:
            raise ValueError(f"{source}: lasers[{i}].laser_id={laser_id} is out of range or repeated")
        seen[laser_id] = True
        for key, default in _LASER_KEYS_WITH_DEFAULTS.items():
            if key in laser:
                values[key][laser_id] = _number(laser[key], f"{source}: lasers[{i}].{key}")
            elif default is None:
                raise ValueError(f"{source}: lasers[{i}] has no {key!r}")
            else:
                values[key][laser_id] = default
    # Rank by elevation (ties by laser id), as velodyne_pointcloud numbers its rings.
    ring = np.empty(num_lasers, dtype=np.uint16)
    ring[np.lexsort((np.arange(num_lasers), values["vert_correction"]))] = np.arange(num_lasers)
    return VelodyneCalibration(
        source=source,
        num_lasers=num_lasers,
        distance_resolution_m=resolution,
        rot_correction_rad=values["rot_correction"],
        vert_correction_rad=values["vert_correction"],
        dist_correction_m=values["dist_correction"],
        dist_correction_x_m=values["dist_correction_x"],
        dist_correction_y_m=values["dist_correction_y"],
        vert_offset_m=values["vert_offset_correction"],
        horiz_offset_m=values["horiz_offset_correction"],
        focal_distance=values["focal_distance"],
        focal_slope=values["focal_slope"],
        min_intensity=values["min_intensity"],
        max_intensity=values["max_intensity"],
        ring=ring,
    )


def load_velodyne_calibration(path: str | Path) -> VelodyneCalibration:
    """Read a Velodyne calibration YAML file; ValueError naming the file and the bad key."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({exc})") from exc
    return parse_velodyne_calibration(doc, str(path))
