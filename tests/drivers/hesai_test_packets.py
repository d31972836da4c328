"""Test-side helpers for the Hesai decoder tests: a binary PCD reader (the reference clouds), and encoders of
Pandar128E4X and PandarAT128 data packets and of an AT128 angle correction file, written from the packet
layouts of Hesai's manuals as tier4/nebula's structs give them (self-made: no capture of these models exists
here, so they check the decoder against our own reading of the layout, not against an oracle)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np


def read_binary_pcd(path: Path) -> np.ndarray:
    """(N, 3) float32 x y z of a binary PCD file with fields x y z only."""
    data = path.read_bytes()
    end = data.index(b"DATA binary\n") + len(b"DATA binary\n")
    header = data[:end].decode()
    assert "FIELDS x y z\n" in header and "SIZE 4 4 4\n" in header, header
    points = int(header.split("POINTS ")[1].split()[0])
    return np.frombuffer(data, np.float32, 3 * points, end).reshape(points, 3)


def _date_1900(seconds: int) -> bytes:
    t = np.datetime64(seconds, "s").astype(object)
    return bytes([t.year - 1900, t.month, t.day, t.hour, t.minute, t.second])


def encode_128e4x(block_azimuth_cdeg: tuple[int, int], distance_raw: np.ndarray, reflectivity: np.ndarray,
                  utc_s: int, microseconds: int, return_mode: int = 0x37, imu: tuple | None = None,
                  signature: bool = False) -> bytes:
    """A Pandar128E4X (OT128) data packet of 861 bytes (893 with the 32-byte signature): 12-byte header,
    2 blocks of an azimuth and 128 units (uint16 distance in 4 mm, uint8 reflectivity), body CRC, 17 bytes of
    functional safety, the tail (return mode at 817, date at 820, microseconds at 826), UDP sequence, IMU
    fields (temperature, acceleration unit, angular velocity unit, IMU time, 3 accelerations, 3 angular
    velocities, signed 16 bit), tail CRC. `imu`: (accel unit, gyro unit, imu time, (ax, ay, az), (wx, wy, wz))."""
    out = bytearray(b"\xee\xff\x01\x04\x00\x00") + bytes([128, 2, 0, 4, 1 if return_mode < 0x39 else 2, 0])
    for block in range(2):
        out += struct.pack("<H", block_azimuth_cdeg[block])
        for channel in range(128):
            out += struct.pack("<HB", int(distance_raw[block, channel]), int(reflectivity[block, channel]))
    out += b"\x00" * 4 + b"\x00" * 17  # body CRC, functional safety
    out += b"\x00" * 9 + struct.pack("<HBB", 0, 1, return_mode) + struct.pack("<H", 600)  # az state, standard mode
    out += _date_1900(utc_s) + struct.pack("<IB", microseconds, 0x42) + struct.pack("<I", 7)
    accel_unit, gyro_unit, imu_time, accel, gyro = imu or (0, 0, 0, (0, 0, 0), (0, 0, 0))
    out += struct.pack("<HHHI3h3h", 25, accel_unit, gyro_unit, imu_time, *accel, *gyro)
    out += b"\x00" * 4
    assert len(out) == 861, len(out)
    return bytes(out + (b"\x00" * 32 if signature else b""))


def encode_at128(block_azimuth: tuple[int, int], distance_raw: np.ndarray, reflectivity: np.ndarray, utc_s: int,
                 microseconds: int, return_mode: int = 0x37) -> bytes:
    """A PandarAT128 data packet of 1,118 bytes: 12-byte header, 2 blocks of a uint16 azimuth, a uint8 fine
    azimuth (together 0.01/256 degree of the motor) and 128 units (uint16 distance in 4 mm, reflectivity,
    confidence), body CRC, the tail (microseconds at 1066, return mode at 1070, a zero byte and seconds since
    1970 in 5 big-endian bytes at 1072), UDP sequence, tail CRC, 32-byte signature."""
    out = bytearray(b"\xee\xff\x04\x03\x00\x00") + bytes([128, 2, 0, 4, 1 if return_mode < 0x39 else 2, 0])
    for block in range(2):
        out += struct.pack("<HB", block_azimuth[block] >> 8, block_azimuth[block] & 0xFF)
        for channel in range(128):
            out += struct.pack("<HBB", int(distance_raw[block, channel]), int(reflectivity[block, channel]), 0)
    out += b"\x00" * 4  # body CRC
    out += b"\x00" * 18 + struct.pack("<HIBB", 200, microseconds, return_mode, 0x42)
    out += b"\x00" + utc_s.to_bytes(5, "big") + struct.pack("<I", 9) + b"\x00" * 4
    assert len(out) == 1086, len(out)
    return bytes(out + b"\x00" * 32)


def encode_at128_correction(frame_start: list[int], frame_end: list[int], azimuth: np.ndarray,
                            elevation: np.ndarray, azimuth_adjust: np.ndarray, elevation_adjust: np.ndarray) -> bytes:
    """An AT128 angle correction file, format 1.5, resolution 1: delimiter 0xEE 0xFF, version, channel, mirror
    and frame counts, 8 frame config bytes, resolution, frame starts and ends (uint32, 0.01/256 degree),
    per-channel azimuth and elevation (int32, same unit), per-channel adjustments every 2 degrees (int8,
    0.01 degree: 180 azimuth entries per channel, then 180 elevation entries per channel), SHA-256."""
    mirrors, channels = len(frame_start), len(azimuth)
    out = bytearray(b"\xee\xff\x01\x05") + bytes([channels, mirrors, mirrors]) + b"\x00" * 8 + b"\x01"
    out += struct.pack(f"<{mirrors}I", *frame_start) + struct.pack(f"<{mirrors}I", *frame_end)
    out += struct.pack(f"<{channels}i", *azimuth) + struct.pack(f"<{channels}i", *elevation)
    out += azimuth_adjust.astype(np.int8).tobytes() + elevation_adjust.astype(np.int8).tobytes()
    return bytes(out + b"\x00" * 32)


AT128_FRAMES_DEG = ((0, 120), (120, 240), (240, 360))  # the self-made correction's mirror frames (motor angle)


def at128_correction_from_table(path: Path, azimuth_adjust: np.ndarray | None = None,
                                elevation_adjust: np.ndarray | None = None) -> bytes:
    """A self-made AT128 correction file: three mirrors over AT128_FRAMES_DEG, each channel's azimuth and
    elevation from a Pandar-style angle CSV (the file's azimuth is subtracted, so the CSV's is negated), the
    given adjustments (128, 180) in 0.01 degree or none."""
    rows = [line.split(",") for line in path.read_text().splitlines()[1:] if line.strip()]
    unit = 25600
    azimuth = np.array([round(-float(r[2]) * unit) for r in rows])
    elevation = np.array([round(float(r[1]) * unit) for r in rows])
    none = np.zeros((len(rows), 180), np.int8)
    starts = [a * unit for a, _ in AT128_FRAMES_DEG]
    ends = [min(b * unit, 360 * unit - 1) for _, b in AT128_FRAMES_DEG]
    return encode_at128_correction(starts, ends, azimuth, elevation,
                                   none if azimuth_adjust is None else azimuth_adjust,
                                   none if elevation_adjust is None else elevation_adjust)
