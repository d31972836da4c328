"""Hesai angle tables: the per-channel CSV of the spinning Pandar models (channel, elevation, azimuth offset in
degrees) and the AT128's binary angle correction file (per-mirror frame start/end, per-channel azimuth and
elevation, and per-channel adjustments every 2 degrees), read into typed dataclasses. A bad file raises a
ValueError naming the file and, for the CSV, the line."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

AT128_ANGLE_UNITS_PER_DEG = 25600  # the AT128 packet's azimuth unit: 0.01 / 256 degree
AT128_ADJUST_STEP_UNITS = 2 * AT128_ANGLE_UNITS_PER_DEG  # one adjustment entry every 2 degrees
AT128_ADJUST_ENTRIES = 180


@dataclass
class HesaiAngles:
    """Angle table of one sensor, indexed by channel (0-based, the unit's index in a block)."""

    source: str
    elevation_deg: np.ndarray  # (C,) float64
    azimuth_offset_deg: np.ndarray  # (C,) float64, added to the block's azimuth
    ring: np.ndarray  # (C,) uint16, rank of the channel by elevation, 0 = lowest

    @property
    def num_channels(self) -> int:
        return len(self.elevation_deg)


@dataclass
class AT128Correction:
    """The AT128's angle correction file, format 1.5 (every value times the file's resolution byte). Angles
    are in 1/25,600 degree (AT128_ANGLE_UNITS_PER_DEG) except the adjustments, in 0.01 degree."""

    source: str
    frame_start: np.ndarray  # (M,) int64, raw motor azimuth where each mirror's frame begins
    frame_end: np.ndarray  # (M,) int64 (read; the decoder cuts no field of view by it)
    azimuth: np.ndarray  # (C,) int64, subtracted from the doubled motor angle
    elevation: np.ndarray  # (C,) int64
    azimuth_adjust: np.ndarray  # (C, 180) int64, 0.01 degree, interpolated over the raw azimuth
    elevation_adjust: np.ndarray  # (C, 180) int64
    ring: np.ndarray  # (C,) uint16, rank by base elevation, 0 = lowest

    @property
    def num_channels(self) -> int:
        return len(self.elevation)


def ring_order(elevation: np.ndarray) -> np.ndarray:
    """Rank of each channel by elevation, 0 = lowest (ties by channel)."""
    ring = np.empty(len(elevation), np.uint16)
    ring[np.argsort(elevation, kind="stable")] = np.arange(len(elevation), dtype=np.uint16)
    return ring


def load_hesai_angles(path: str | Path) -> HesaiAngles:
    """Read a Pandar angle CSV: a header line, then `channel,elevation,azimuth` with channels 1..C in order."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not a text angle table ({error})") from None
    rows: list[tuple[float, float]] = []
    for number, line in enumerate(lines, start=1):
        fields = [f.strip() for f in line.split(",")]
        if not line.strip() or (number == 1 and not _is_number(fields[0])):
            continue  # blank line or the header
        if len(fields) != 3:
            raise ValueError(f"{path}:{number}: expected channel,elevation,azimuth, got {line!r}")
        try:
            channel, elevation, azimuth = int(fields[0]), float(fields[1]), float(fields[2])
        except ValueError:
            raise ValueError(f"{path}:{number}: not numbers: {line!r}") from None
        if channel != len(rows) + 1:
            raise ValueError(f"{path}:{number}: channel {channel} where {len(rows) + 1} is due")
        if not (abs(elevation) <= 90 and abs(azimuth) <= 180):
            raise ValueError(f"{path}:{number}: angle out of range: {line!r}")
        rows.append((elevation, azimuth))
    if not rows:
        raise ValueError(f"{path}: no channels")
    table = np.array(rows, dtype=np.float64)
    return HesaiAngles(str(path), table[:, 0], table[:, 1], ring_order(table[:, 0]))


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def load_at128_correction(path: str | Path) -> AT128Correction:
    """Read the AT128's binary angle correction file (as the sensor serves it): from the 0xEE 0xFF delimiter,
    version, channel, mirror and frame counts, frame config, resolution, then little-endian tables."""
    path = Path(path)
    data = path.read_bytes()
    start = data.find(b"\xee\xff")
    if start < 0:
        raise ValueError(f"{path}: no 0xEE 0xFF delimiter: not an AT128 angle correction file (the binary file the "
                         "sensor serves; its angle CSV alone does not give the mirrors' frames)")
    head = data[start : start + 16]
    if len(head) < 16:
        raise ValueError(f"{path}: truncated header")
    major, minor, channels, mirrors = head[2], head[3], head[4], head[5]
    resolution = head[15]
    if (major, minor) != (1, 5) or not 1 <= mirrors <= 8 or channels == 0 or resolution == 0:
        raise ValueError(f"{path}: unsupported correction file (version {major}.{minor}, {channels} channels, "
                         f"{mirrors} mirrors, resolution {resolution}); format 1.5 is read")
    adjust = channels * AT128_ADJUST_ENTRIES
    offset = start + 16
    need = offset + 4 * (2 * mirrors + 2 * channels) + 2 * adjust
    if len(data) < need:
        raise ValueError(f"{path}: truncated: {len(data)} bytes, the tables need {need}")

    def table(count: int, dtype: str) -> np.ndarray:
        nonlocal offset
        values = np.frombuffer(data, dtype, count, offset).astype(np.int64)
        offset += count * np.dtype(dtype).itemsize
        return values * resolution

    frame_start, frame_end = table(mirrors, "<u4"), table(mirrors, "<u4")
    azimuth, elevation = table(channels, "<i4"), table(channels, "<i4")
    azimuth_adjust, elevation_adjust = table(adjust, "i1"), table(adjust, "i1")
    if np.any(np.diff(frame_start) <= 0) or np.any(frame_start >= 360 * AT128_ANGLE_UNITS_PER_DEG):
        raise ValueError(f"{path}: mirror frame starts {frame_start.tolist()} not ascending within one turn")
    return AT128Correction(
        str(path), frame_start, frame_end, azimuth, elevation,
        azimuth_adjust.reshape(channels, AT128_ADJUST_ENTRIES),
        elevation_adjust.reshape(channels, AT128_ADJUST_ENTRIES),
        ring_order(elevation),
    )
