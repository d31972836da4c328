"""Byte layouts of the Hesai data packets decoded here, one HesaiFormat per model (sizes, header signature,
blocks and units, where the tail keeps the return mode, time and IMU fields), and the packet time stamp.
Learnt from tier4/nebula's packet structs and Hesai's user manuals; offsets are from the datagram's start."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.lidar.hesai_firing_times import (
    PANDAR40P,
    PANDAR64,
    PANDAR128E4X,
    PANDARAT128,
    PANDARQT128,
    PANDARXT32,
    FiringTimes,
)
from drivers.lidar.packet_decoding import RETURN_TYPE_LAST, RETURN_TYPE_OTHER, RETURN_TYPE_STRONGEST

# Tail return-mode byte -> returns per firing (the blocks of one firing are consecutive).
RETURN_MODES = {0x33: 1, 0x34: 1, 0x37: 1, 0x38: 1, 0x39: 2, 0x3A: 2, 0x3B: 2, 0x3C: 2, 0x03: 2, 0x3E: 2, 0x3D: 3}
SINGLE_FIRST, SINGLE_SECOND, SINGLE_STRONGEST, SINGLE_LAST = 0x33, 0x34, 0x37, 0x38
DUAL_LAST_STRONGEST, DUAL_FIRST_SECOND, DUAL_FIRST_LAST, DUAL_FIRST_STRONGEST = 0x39, 0x3A, 0x3B, 0x3C
# Strongest + second strongest: 0x03 in nebula, 0x3E in the QT128C2X manual; both read.
DUAL_STRONGEST_SECOND, DUAL_STRONGEST_SECOND_QT128, TRIPLE_FIRST_LAST_STRONGEST = 0x03, 0x3E, 0x3D
N_RETURNS = np.zeros(256, np.int64)  # by return-mode byte; 0: no mode
N_RETURNS[list(RETURN_MODES)] = list(RETURN_MODES.values())

# How the tail's date is written: year, month, day, hour, minute, second; or a zero byte and big-endian seconds
# since 1970 in 5 bytes. The year byte counts from 2000 in the Pandar40P and Pandar64 manuals and from 1900 in
# the later models (nebula's structs), but the Pandar64 capture here writes 120 (2020): so a year byte from 70
# is taken from 1900 and one below from 2000, which reads both for 1970-2069.
DATE_YMDHMS, DATE_EPOCH = "ymdhms", "epoch"


@dataclass(frozen=True)
class HesaiFormat:
    model: str  # factory name, hesai-...
    sizes: tuple[int, ...]  # accepted datagram sizes (with and without the optional trailing fields)
    header: tuple[tuple[int, int], ...]  # (byte offset, value) every packet of the model carries
    n_blocks: int
    n_channels: int
    first_block: int  # offset of block 0
    block_size: int
    azimuth_at: int  # offset of the block's uint16 azimuth in the block
    fine_azimuth: bool  # a byte of 1/256 azimuth unit follows the azimuth (AT128)
    first_unit: int  # offset of the first unit in the block
    unit_size: int  # uint16 distance, uint8 reflectivity[, uint8 confidence]
    block_flag: bytes  # bytes every block starts with (Pandar40P), or b""
    dis_unit_at: int | None  # header byte holding the distance unit in mm; None: 4 mm
    return_mode_at: int
    timestamp_at: int  # uint32 microseconds within the second
    date_at: int
    date_kind: str
    min_range_m: float
    max_range_m: float
    firing: FiringTimes
    first_last_reversed: bool = False  # dual first+last: the sensor puts the last return first
    imu_at: int | None = None  # offset of the IMU fields in the tail


_SIGNATURE = ((0, 0xEE), (1, 0xFF))


def _header12(protocol_major: int, lasers: int, blocks: int) -> tuple[tuple[int, int], ...]:
    return _SIGNATURE + ((2, protocol_major), (6, lasers), (7, blocks))


FORMATS = {
    f.model: f
    for f in (
        HesaiFormat("hesai-pandar40p", (1262, 1266), ((0, 0xFF), (1, 0xEE)), 10, 40, 0, 124, 2, False, 4, 3,
                    b"\xff\xee", None, 1254, 1250, 1256, DATE_YMDHMS, 0.3, 200.0, PANDAR40P),
        HesaiFormat("hesai-pandar64", (1194, 1198), _SIGNATURE + ((2, 64), (3, 6)), 6, 64, 8, 194, 0, False, 2, 3,
                    b"", 5, 1186, 1182, 1188, DATE_YMDHMS, 0.3, 200.0, PANDAR64),
        HesaiFormat("hesai-pandarqt128", (1095, 1127), _header12(3, 128, 2), 2, 128, 12, 514, 0, False, 2, 4,
                    b"", 9, 1073, 1082, 1076, DATE_YMDHMS, 0.05, 50.0, PANDARQT128),
        HesaiFormat("hesai-pandarxt32", (1076, 1080), _header12(6, 32, 8), 8, 32, 12, 130, 0, False, 2, 4,
                    b"", 9, 1062, 1071, 1065, DATE_YMDHMS, 0.05, 120.0, PANDARXT32,
                    first_last_reversed=True),
        HesaiFormat("hesai-pandar128e4x", (861, 893), _header12(1, 128, 2), 2, 128, 12, 386, 0, False, 2, 3,
                    b"", 9, 817, 826, 820, DATE_YMDHMS, 0.1, 230.0, PANDAR128E4X,
                    first_last_reversed=True, imu_at=835),
        HesaiFormat("hesai-pandarat128", (1086, 1118), _header12(4, 128, 2), 2, 128, 12, 515, 0, True, 3, 4,
                    b"", 9, 1070, 1066, 1072, DATE_EPOCH, 1.0, 180.0, PANDARAT128),
    )
}
HESAI_MODELS = tuple(FORMATS)


def return_type_table(first_last_reversed: bool) -> np.ndarray:
    """(256, 3, 2) uint8 RETURN_TYPE_* bits by return-mode byte, the return's index in its firing, and whether
    it is the firing's strongest (no other return has a higher reflectivity). Dual first+last: the XT32 and
    128E4X send the last return first (nebula flips them as well)."""
    S, L, O = RETURN_TYPE_STRONGEST, RETURN_TYPE_LAST, RETURN_TYPE_OTHER
    table = np.zeros((256, 3, 2), np.uint8)
    table[SINGLE_STRONGEST, 0] = S
    table[SINGLE_LAST, 0] = L
    table[[SINGLE_FIRST, SINGLE_SECOND], 0] = O
    table[DUAL_LAST_STRONGEST, 0] = (L, L | S)
    table[DUAL_FIRST_STRONGEST, 0] = (O, O | S)
    table[[DUAL_LAST_STRONGEST, DUAL_FIRST_STRONGEST], 1] = (O, S)
    table[DUAL_FIRST_SECOND, :2] = O
    table[[DUAL_STRONGEST_SECOND, DUAL_STRONGEST_SECOND_QT128], :2] = ((S, S), (O, O))
    table[DUAL_FIRST_LAST, :2] = ((L, L), (O, O)) if first_last_reversed else ((O, O), (L, L))
    table[TRIPLE_FIRST_LAST_STRONGEST] = ((O, O), (L, L), (S, S))
    return table


def format_of(packet: bytes) -> HesaiFormat | None:
    """The format whose size and header the datagram has, if any."""
    for f in FORMATS.values():
        if len(packet) in f.sizes and all(packet[at] == value for at, value in f.header):
            return f
    return None


def u16(a: np.ndarray, offset: int) -> np.ndarray:
    """Little-endian uint16 at byte `offset` of the last axis, as int64."""
    return a[..., offset].astype(np.int64) | (a[..., offset + 1].astype(np.int64) << 8)


def u32(a: np.ndarray, offset: int) -> np.ndarray:
    return u16(a, offset) | (u16(a, offset + 2) << 16)


def _days_from_civil(year: np.ndarray, month: np.ndarray, day: np.ndarray) -> np.ndarray:
    """Days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's algorithm)."""
    y = year - (month <= 2)
    era = np.floor_divide(y, 400)
    yoe = y - era * 400
    doy = (153 * (month + np.where(month > 2, -3, 9)) + 2) // 5 + day - 1
    doe = yoe * 365 + yoe // 4 - yoe // 100 + doy
    return era * 146097 + doe - 719468


def packet_times_ns(fmt: HesaiFormat, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(UTC nanoseconds of each packet's stamp, whether its date and microseconds are well formed)."""
    microseconds = u32(batch, fmt.timestamp_at)
    d = batch[:, fmt.date_at : fmt.date_at + 6].astype(np.int64)
    if fmt.date_kind == DATE_EPOCH:
        seconds = np.zeros(len(batch), np.int64)
        for i in range(1, 6):
            seconds = seconds << 8 | d[:, i]
        ok = d[:, 0] == 0
    else:
        year = d[:, 0] + np.where(d[:, 0] >= 70, 1900, 2000)
        month, day, hour, minute, second = d[:, 1], d[:, 2], d[:, 3], d[:, 4], d[:, 5]
        ok = (month >= 1) & (month <= 12) & (day >= 1) & (day <= 31) & (hour < 24) & (minute < 60) & (second < 61)
        days = _days_from_civil(year, np.clip(month, 1, 12), day)
        seconds = ((days * 24 + hour) * 60 + minute) * 60 + second
    ok &= microseconds < 1_000_000
    return seconds * 1_000_000_000 + microseconds * 1000, ok
