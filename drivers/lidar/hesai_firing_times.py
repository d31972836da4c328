"""When each return of a Hesai data packet was fired, in nanoseconds after the packet's own timestamp (negative:
before it), per model as data (FiringTimes): a per-block term by return mode and a per-channel term from one of the
model's tables, from the firing time tables of Hesai's user manuals (the figures tier4/nebula uses)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

_P40 = np.array([
    -42220, -28470, -16040, -3620, -45490, -31740, -47460, -54670, -20620, -33710,
    -40910, -8190, -20620, -27160, -50730, -8190, -14740, -36980, -45490, -52700,
    -23890, -31740, -38950, -11470, -18650, -25190, -48760, -6230, -12770, -35010,
    -21920, -9500, -43520, -29770, -17350, -4920, -42220, -28470, -16040, -3620,
], np.int64)

_P64 = np.array([
    -23180, -21876, -20572, -19268, -17964, -16660, -11444, -46796, -7532, -36956, -50732,
    -54668, -40892, -44828, -31052, -34988, -48764, -52700, -38924, -42860, -29084, -33020,
    -46796, -25148, -36956, -50732, -27116, -40892, -44828, -31052, -34988, -48764, -25148,
    -38924, -42860, -29084, -33020, -52700, -6228, -54668, -15356, -27116, -10140, -23180,
    -4924, -21876, -14052, -17964, -8836, -19268, -3620, -20572, -12748, -16660, -7532,
    -11444, -6228, -15356, -10140, -4924, -3620, -14052, -8836, -12748,
], np.int64)

# PandarQT128: two firing loops; in loop 1 channels 0-31 stay dark, in loop 2 channels 32-63 (0 here).
_QT128_LOOP1 = np.array([0] * 32 + [
    27656, 53000, 2312, 78344, 81512, 5480, 56168, 30824, 33992, 59336, 8648, 84680, 87848, 11816, 62504, 37160,
    40328, 65672, 14984, 91016, 94184, 18152, 68840, 43496, 46664, 72008, 21320, 97352, 100520, 24488, 75176, 49832,
    1456, 77488, 26800, 52144, 55312, 29968, 80656, 4624, 7792, 83824, 33136, 58480, 61648, 36304, 86992, 10960,
    14128, 90160, 39472, 64816, 67984, 42640, 93328, 17296, 20464, 96496, 45808, 71152, 74320, 48976, 99664, 23632,
    25944, 51288, 600, 76632, 79800, 3768, 54456, 29112, 32280, 57624, 6936, 82968, 86136, 10104, 60792, 35448,
    38616, 63960, 13272, 89304, 92472, 16440, 67128, 41784, 44952, 70296, 19608, 95640, 98808, 22776, 73464, 48120,
], np.int64)
_QT128_LOOP2 = np.array([
    2312, 78344, 27656, 53000, 56168, 30824, 81512, 5480, 8648, 84680, 33992, 59336, 62504, 37160, 87848, 11816,
    14984, 91016, 40328, 65672, 68840, 43496, 94184, 18152, 21320, 97352, 46664, 72008, 75176, 49832, 100520, 24488,
] + [0] * 32 + [
    600, 76632, 25944, 51288, 54456, 29112, 79800, 3768, 6936, 82968, 32280, 57624, 60792, 35448, 86136, 10104,
    13272, 89304, 38616, 63960, 67128, 41784, 92472, 16440, 19608, 95640, 44952, 70296, 73464, 48120, 98808, 22776,
    26800, 52144, 1456, 77488, 80656, 4624, 55312, 29968, 33136, 58480, 7792, 83824, 86992, 10960, 61648, 36304,
    39472, 64816, 14128, 90160, 93328, 17296, 67984, 42640, 45808, 71152, 20464, 96496, 99664, 23632, 74320, 48976,
], np.int64)

# Pandar128E4X (OT128): standard mode, and high-resolution mode by the block's azimuth state 0 or 1 (-1 where a
# channel does not fire in that state).
_E4X_STANDARD = np.array([
    49758, 43224, 36690, 30156, 21980, 15446, 8912, 2378, 49758, 43224, 36690, 30156, 2378, 15446, 8912, 21980,
    43224, 30156, 49758, 15446, 36690, 2378, 21980, 8912, 34312, 45002, 38468, 40846, 40846, 34312, 51536, 47380,
    31934, 47380, 31934, 51536, 38468, 27778, 27778, 45002, 38468, 40846, 51536, 45002, 31934, 47380, 34312, 27778,
    38468, 40846, 51536, 45002, 31934, 34312, 27778, 38468, 40846, 51536, 45002, 31934, 47380, 34312, 27778, 45002,
    45002, 51536, 38468, 40846, 47380, 40846, 31934, 45002, 27778, 38468, 40846, 31934, 27778, 38468, 34312, 34312,
    34312, 47380, 51536, 31934, 51536, 47380, 27778, 49758, 21980, 43224, 15446, 43224, 36690, 8912, 30156, 2378,
    49758, 21980, 36690, 15446, 8912, 30156, 2378, 49758, 43224, 36690, 30156, 21980, 15446, 8912, 2378, 43224,
    49758, 30156, 36690, 21980, 15446, 2378, 8912, 49758, 43224, 36690, 30156, 21980, 15446, 8912, 2378, 30156,
], np.int64)
_E4X_HIRES = np.array([[
    -1, -1, -1, -1, 21980, 15446, 8912, 2378, -1, -1, -1, -1, 2378, 15446, 8912, 21980,
    -1, 2378, 21980, 8912, 6534, 17224, 10690, 13068, 13068, 6534, 23758, 19602, 4156, 19602, 4156, 23758,
    13068, 13068, 23758, 10690, 4156, 19602, 19602, 0, 10690, 6534, 23758, 17224, 23758, 19602, 6534, 17224,
    4156, 0, 6534, 0, 17224, 10690, 17224, 17224, 23758, 23758, 10690, 13068, 13068, 13068, 19602, 19602,
    6534, 13068, 4156, 4156, 17224, 17224, 17224, 0, 10690, 10690, 13068, 13068, 4156, 0, 10690, 6534,
    6534, 6534, 19602, 23758, 4156, 23758, 19602, 0, -1, 21980, -1, 15446, -1, 8912, -1, 2378,
    -1, -1, 21980, -1, 15446, 8912, -1, 2378, -1, -1, -1, -1, 21980, 15446, 8912, 2378,
    -1, -1, -1, -1, 21980, 15446, 2378, 8912, -1, -1, -1, -1, 21980, 15446, 8912, 2378,
], [
    21980, 15446, 8912, 2378, -1, -1, -1, -1, 21980, 15446, 8912, 2378, -1, -1, -1, -1,
    8912, -1, -1, -1, 6534, 17224, 10690, 13068, 13068, 6534, 23758, 19602, 4156, 19602, 4156, 23758,
    13068, 13068, 23758, 10690, 4156, 19602, 19602, 0, 10690, 6534, 23758, 17224, 23758, 19602, 6534, 17224,
    4156, 0, 6534, 0, 17224, 10690, 17224, 17224, 23758, 23758, 10690, 13068, 13068, 13068, 19602, 19602,
    6534, 13068, 4156, 4156, 17224, 17224, 17224, 0, 10690, 10690, 13068, 13068, 4156, 0, 10690, 6534,
    6534, 6534, 19602, 23758, 4156, 23758, 19602, 0, 21980, -1, 15446, -1, 8912, -1, 2378, -1,
    21980, 15446, -1, 8912, -1, -1, 2378, -1, 21980, 15446, 8912, 2378, -1, -1, -1, -1,
    15446, 21980, 2378, 8912, -1, -1, -1, -1, 21980, 15446, 8912, 2378, -1, -1, -1, -1,
]], np.int64)

_AT128 = np.array([
    0, 0, 8240, 4112, 4144, 8240, 0, 0, 12424, 4144, 4112, 8264, 12376, 12376, 8264, 12424,
    0, 0, 4112, 8240, 4144, 0, 0, 4144, 12424, 8264, 4112, 12376, 12376, 12424, 8264, 848,
    2504, 4976, 6616, 6616, 9112, 2504, 848, 10768, 13280, 13280, 4976, 9112, 14928, 14928, 10768, 2504,
    848, 6616, 4976, 9112, 6616, 848, 2504, 13280, 10768, 4976, 13280, 14928, 9112, 10768, 14928, 13280,
    848, 9112, 13280, 2504, 4976, 848, 2504, 14928, 10768, 10768, 14928, 4976, 6616, 6616, 9112, 848,
    13280, 13280, 9112, 4976, 2504, 2504, 848, 10768, 14928, 14928, 10768, 6616, 4976, 9112, 6616, 4112,
    12424, 0, 4144, 0, 0, 12424, 0, 8264, 4112, 4144, 8240, 8240, 8264, 12376, 12376, 12424,
    4112, 4144, 0, 0, 0, 0, 0, 12424, 8264, 8240, 4144, 8264, 8240, 12376, 12376, 8264,
], np.int64)


@dataclass(frozen=True)
class FiringTimes:
    """A model's firing times: a return of block b in a packet of r returns per firing, channel c, fired
    `block_offset_ns + block_step_ns * ((last block - b) // r) + channel_ns[row, c]` after the packet's stamp, `row`
    the channel table the block fires by (`table_rows`; None: the one table)."""

    block_offset_ns: int
    block_step_ns: int
    channel_ns: np.ndarray  # (tables, channels) int64
    table_rows: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None  # (n_returns, packets) -> (n, blocks)

    def block_ns(self, n_blocks: int) -> np.ndarray:
        """(4, n_blocks) int64: the block term by returns per firing (row 0 unused) and block."""
        returns = np.maximum(np.arange(4), 1)[:, None]
        return self.block_offset_ns + self.block_step_ns * ((n_blocks - 1 - np.arange(n_blocks)) // returns)

    def rows(self, n_returns: np.ndarray, packets: np.ndarray, n_blocks: int) -> np.ndarray:
        """(n, n_blocks) intp: the channel table of each packet's blocks."""
        if self.table_rows is None:
            return np.zeros((len(packets), n_blocks), np.intp)
        return np.ascontiguousarray(self.table_rows(n_returns, packets), dtype=np.intp)


def _qt128_loops(n_returns: np.ndarray, packets: np.ndarray, mode_flag_offset: int = 1066) -> np.ndarray:
    """PandarQT128, table 0 loop 1 and 1 loop 2. Single return: block 0 fires loop 1, block 1 loop 2, 111.11 us
    apart; multiple return: both blocks are returns of one firing of the loop that bit 0 of the tail's mode flag
    names (1: loop 1). Nebula divides the block term by the number of returns after multiplying, which puts the two
    returns of one dual firing 55.6 us apart; here they share the firing's time, as the QT128C2X manual has it ("the
    measurements from each round of firing are stored in the two blocks of one packet")."""
    flag_loop1 = (packets[:, mode_flag_offset] & 1)[:, None] == 1
    return np.where(np.where(n_returns[:, None] == 1, np.arange(2)[None, :] == 0, flag_loop1), 0, 1)


def _e4x_states(n_returns: np.ndarray, packets: np.ndarray, azimuth_state_offset: int = 814,
                operational_state_offset: int = 816) -> np.ndarray:
    """Pandar128E4X: table 0 in standard mode (operational state 1); in high-resolution mode (0) table 1 or 2 by
    each block's azimuth state (2 bits per block, block 0 in bits 15-14 of the tail's azimuth state; the manual's
    tables are for states 0 and 1, nebula takes the state-1 table for any other state, as here)."""
    state = packets[:, azimuth_state_offset].astype(np.int64) | packets[:, azimuth_state_offset + 1].astype(
        np.int64) << 8
    azimuth_state = (state[:, None] >> (14 - 2 * np.arange(2))) & 3 != 0  # (n, 2)
    hires = (packets[:, operational_state_offset] == 0)[:, None]
    return np.where(hires, 1 + azimuth_state, 0)


PANDAR40P = FiringTimes(-28580, -55560, _P40[None, :])
PANDAR64 = FiringTimes(-42580, -55560, _P64[None, :])
PANDARQT128 = FiringTimes(9000, 111110, np.stack([_QT128_LOOP1, _QT128_LOOP2]), _qt128_loops)
PANDARXT32 = FiringTimes(5632, -50000, 368 + 1512 * np.arange(32, dtype=np.int64)[None, :])
# Pandar128E4X: single return, block 0 fires 55.556 us before block 1; multiple return: both at once.
PANDAR128E4X = FiringTimes(43346, -27778 * 2, np.concatenate([_E4X_STANDARD[None, :], _E4X_HIRES]), _e4x_states)
PANDARAT128 = FiringTimes(-9249 - 41666, -41666, _AT128[None, :])
