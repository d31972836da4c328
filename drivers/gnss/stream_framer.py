"""Cuts a mixed NMEA 0183 + u-blox UBX byte stream into checksum-verified frames, counting every rejection.

A frame starts at a sync ('$' for NMEA, 0xB5 0x62 for UBX). A candidate that fails its checksum, is cut
short (a byte that cannot belong to it, such as the next sync), is too long, or is still incomplete when
the stream ends is rejected, and the search resumes ONE byte after its start: a stray sync byte or a false
UBX header never costs the valid frames behind it (the trap of the libraries' own stream readers).

What a hostile stream costs stays within a few times a real one's (bench/gnss_framer.py): a long UBX body's
checksum comes from prefix sums of the buffer, made once per `feed` that needs one, not from a walk over the
claimed length for every false header; a run of '$' is rejected in one step (each '$' but the last is cut short
by the next), and so is a run of UBX syncs (each but the last two claims a length of 0x62B5 bytes).

Rejection kinds (keys of `StreamFramer.counts`): garbage (a run of bytes outside any frame),
nmea_bad_checksum, nmea_no_checksum, nmea_truncated, nmea_too_long, ubx_bad_checksum, ubx_too_long,
ubx_truncated.
"""

from __future__ import annotations

import itertools
import re
from collections import Counter
from dataclasses import dataclass
from functools import reduce
from operator import xor
from typing import Literal

import numpy as np

from daemon.spine.health import HealthCounters

NMEA_SYNC = 0x24  # '$'
UBX_SYNC = b"\xb5\x62"
NMEA_MAX_BYTES = 1024  # "$" to "\n"; NMEA 0183 allows 82, u-blox PUBX,03 runs to several hundred
UBX_MAX_PAYLOAD = 8192  # RXM-RAWX with 255 measurements is 8176 bytes
_NMEA_BODY_BYTES = bytes(b for b in range(0x20, 0x7F) if b != NMEA_SYNC)  # printable ASCII but '$'
_NMEA_PARTIAL_BYTES = _NMEA_BODY_BYTES + b"\r"
_HEX_DIGITS = b"0123456789ABCDEFabcdef"
_DIRECT_CHECKSUM_BYTES = 128  # a UBX body up to this long is summed directly, a longer one from _PrefixSums
_DOLLAR_RUN = re.compile(rb"\$+")
_UBX_SYNC_RUN = re.compile(rb"(?:\xb5\x62)+")


@dataclass(frozen=True, slots=True)
class Frame:
    """One checksum-verified message: an NMEA sentence "$...*hh" (no line end) or a whole UBX frame."""

    protocol: Literal["nmea", "ubx"]
    data: bytes


def ubx_checksum(body: bytes | bytearray) -> bytes:
    """The 8-bit Fletcher checksum (CK_A, CK_B) of a UBX frame's class, id, length and payload."""
    return bytes((sum(body) & 0xFF, sum(itertools.accumulate(body)) & 0xFF))


def nmea_checksum(body: bytes | bytearray) -> int:
    """XOR of the characters between '$' and '*'."""
    return reduce(xor, body, 0)


class _PrefixSums:
    """Running sums of a buffer, so that the UBX checksum of any span of it costs the same, however long."""

    def __init__(self, buf: bytearray) -> None:
        data = np.frombuffer(bytes(buf), dtype=np.uint8)  # a copy: the buffer is resized after the drain
        self.sums = np.zeros(len(data) + 1, dtype=np.uint64)  # sums[i] = sum(data[:i])
        np.cumsum(data, dtype=np.uint64, out=self.sums[1:])
        self.sums_of_sums = np.zeros(len(data) + 2, dtype=np.uint64)  # [i] = sum(sums[:i]), exact below 2**64
        np.cumsum(self.sums, out=self.sums_of_sums[1:])

    def ubx_checksum(self, lo: int, hi: int) -> bytes:
        """ubx_checksum(buf[lo:hi]): CK_A = the sum of the bytes, CK_B = the sum of the running sums."""
        base = int(self.sums[lo])
        ck_a = int(self.sums[hi]) - base
        ck_b = int(self.sums_of_sums[hi + 1]) - int(self.sums_of_sums[lo + 1]) - (hi - lo) * base
        return bytes((ck_a & 0xFF, ck_b & 0xFF))


class StreamFramer:
    """Feed bytes as they arrive; get back the complete frames found so far (partial ones are kept)."""

    def __init__(self, health: HealthCounters | None = None) -> None:
        self.counts: Counter[str] = Counter()
        self.skipped_bytes = 0  # bytes that belonged to no delivered frame
        self.frame_bytes = 0  # bytes of delivered frames (NMEA line ends included)
        self._buffer = bytearray()
        self._health = health
        # the bytes skipped next continue what is already counted: a rejected candidate, or the garbage run that the
        # previous read ended in (a run counts once however the reads cut it)
        self._after_rejection = False

    @property
    def pending_bytes(self) -> int:
        return len(self._buffer)

    def feed(self, data: bytes) -> list[Frame]:
        self._buffer += data
        return self._drain(final=False)

    def flush(self) -> list[Frame]:
        """End of stream (port closed): reject what is incomplete and return the frames behind it."""
        return self._drain(final=True)

    def _reject(self, kind: str, n: int = 1) -> None:
        self.counts[kind] += n
        if self._health is not None:
            for _ in range(n):
                self._health.count_rejected(f"framer: {kind}")

    def _skip(self, n: int) -> None:
        if n <= 0:
            return
        self.skipped_bytes += n
        if not self._after_rejection:
            self._reject("garbage")
        self._after_rejection = False

    def _drain(self, final: bool) -> list[Frame]:
        buf = self._buffer
        frames: list[Frame] = []
        sums: _PrefixSums | None = None  # made when the first long UBX body needs its checksum
        pos = 0
        while pos < len(buf):
            start = _next_sync(buf, pos)
            if start < 0:
                keep = 1 if not final and buf[-1] == UBX_SYNC[0] else 0  # maybe the first half of a sync
                self._skip(len(buf) - keep - pos)
                self._after_rejection = self._after_rejection or len(buf) - keep > pos
                pos = len(buf) - keep
                break
            self._skip(start - pos)
            self._after_rejection = False
            if buf[start] == NMEA_SYNC:
                run = _DOLLAR_RUN.match(buf, start).end() - start - 1
                if run:  # each '$' followed by another is cut short by it
                    self._reject("nmea_truncated", run)
                    self.skipped_bytes += run
                    self._after_rejection = True
                    pos = start + run
                    continue
                outcome, end = _nmea_candidate(buf, start, final)
            else:
                run = (_UBX_SYNC_RUN.match(buf, start).end() - start) // 2 - 2
                if run > 0:  # in a run of syncs, each but the last two claims the length B5 62: too long
                    self._reject("ubx_too_long", run)
                    self.skipped_bytes += 2 * run
                    self._after_rejection = True
                    pos = start + 2 * run
                    continue
                outcome, end = _ubx_candidate(buf, start, final)
                if outcome == "check":
                    if end - start - 4 <= _DIRECT_CHECKSUM_BYTES:
                        checksum = ubx_checksum(buf[start + 2 : end - 2])
                    else:
                        sums = sums or _PrefixSums(buf)
                        checksum = sums.ubx_checksum(start + 2, end - 2)
                    outcome = "frame" if checksum == buf[end - 2 : end] else "ubx_bad_checksum"
            if outcome == "more":
                pos = start
                break
            if outcome == "frame":
                protocol = "nmea" if buf[start] == NMEA_SYNC else "ubx"
                data = bytes(buf[start:end]).rstrip(b"\r\n") if protocol == "nmea" else bytes(buf[start:end])
                frames.append(Frame(protocol, data))
                self.frame_bytes += end - start
                pos = end
            else:
                self._reject(outcome)
                self.skipped_bytes += 1
                self._after_rejection = True
                pos = start + 1
        del buf[:pos]
        return frames


def _next_sync(buf: bytearray, pos: int) -> int:
    nmea = buf.find(NMEA_SYNC, pos)
    ubx = buf.find(UBX_SYNC, pos, nmea + 1 if nmea >= 0 else len(buf))
    if ubx >= 0 and (nmea < 0 or ubx < nmea):
        return ubx
    return nmea


def _nmea_candidate(buf: bytearray, start: int, final: bool) -> tuple[str, int]:
    """("frame", end) | ("more", 0) | (rejection kind, 0) for the sentence starting at buf[start] == '$'."""
    limit = min(len(buf), start + NMEA_MAX_BYTES)
    newline = buf.find(b"\n", start + 1, limit)
    if newline < 0:
        if buf[start + 1 : limit].translate(None, _NMEA_PARTIAL_BYTES):
            return "nmea_truncated", 0
        if limit == start + NMEA_MAX_BYTES:
            return "nmea_too_long", 0
        return ("nmea_truncated", 0) if final else ("more", 0)
    line = buf[start + 1 : newline]
    if line.endswith(b"\r"):
        line = line[:-1]
    if line.translate(None, _NMEA_BODY_BYTES):
        return "nmea_truncated", 0
    if len(line) < 3 or line[-3] != ord("*") or line[-2:].translate(None, _HEX_DIGITS):
        return "nmea_no_checksum", 0
    if nmea_checksum(line[:-3]) != int(line[-2:], 16):
        return "nmea_bad_checksum", 0
    return "frame", newline + 1


def _ubx_candidate(buf: bytearray, start: int, final: bool) -> tuple[str, int]:
    """("check", end): complete, its checksum to be checked | ("more", 0) | (rejection kind, 0) for the frame
    starting at buf[start:] == B5 62."""
    if len(buf) < start + 6:
        return ("ubx_truncated", 0) if final else ("more", 0)
    length = buf[start + 4] | buf[start + 5] << 8
    if length > UBX_MAX_PAYLOAD:
        return "ubx_too_long", 0
    end = start + 8 + length
    if len(buf) < end:
        return ("ubx_truncated", 0) if final else ("more", 0)
    return "check", end
