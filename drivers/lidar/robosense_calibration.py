"""RoboSense per-laser angle file: one line per laser, `elevation[,azimuth offset]` in degrees (the CSV that
RoboSense's SDK and Nebula read, laser 0 first), read into a dataclass of 0.01-degree integers, the
resolution the sensor's own device-info packet gives them in."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class RobosenseCalibration:
    """Angles of the L lasers of one sensor, indexed by the laser's channel in the packet."""

    source: str  # the file it was read from, for messages
    elevation_cdeg: np.ndarray  # (L,) int32, 0.01 degrees, up positive
    azimuth_offset_cdeg: np.ndarray  # (L,) int32, 0.01 degrees, added to the firing azimuth (clockwise)
    ring: np.ndarray  # (L,) uint16, rank of the laser by elevation, 0 = lowest

    @property
    def num_lasers(self) -> int:
        return int(self.elevation_cdeg.shape[0])


def _angle(text: str, where: str) -> int:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{where}: {text.strip()!r} is not a number") from None
    if not -90.0 <= value < 90.0:
        raise ValueError(f"{where}: angle {value} is outside -90..90 degrees")
    return int(round(value * 100))


def parse_robosense_calibration(text: str, source: str = "<calibration>") -> RobosenseCalibration:
    """The calibration in the text of an angle file; ValueError naming `source` and the line when bad.
    Blank lines are skipped; a line with one number has no azimuth offset."""
    elevation, azimuth = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{source}:{number}"
        fields = line.split(",")
        if len(fields) > 2:
            raise ValueError(f"{where}: expected 'elevation,azimuth', got {line.strip()!r}")
        elevation.append(_angle(fields[0], where))
        azimuth.append(_angle(fields[1], where) if len(fields) == 2 else 0)
    if not elevation:
        raise ValueError(f"{source}: no laser angles")
    elevation_cdeg = np.array(elevation, dtype=np.int32)
    # Rank by elevation, ties by laser, as RoboSense's SDK numbers its rings.
    ring = np.empty(len(elevation), dtype=np.uint16)
    ring[np.lexsort((np.arange(len(elevation)), elevation_cdeg))] = np.arange(len(elevation))
    return RobosenseCalibration(source, elevation_cdeg, np.array(azimuth, dtype=np.int32), ring)


def load_robosense_calibration(path: str | Path) -> RobosenseCalibration:
    """Read a RoboSense angle CSV; ValueError naming the file and the bad line."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the angle file ({exc})") from exc
    return parse_robosense_calibration(text, str(path))
