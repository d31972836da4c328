"""Cuts a mixed NMEA 0183 + u-blox UBX byte stream into checksum-verified frames, counting every rejection.

A frame starts at a sync ('$' for NMEA, 0xB5 0x62 for UBX). A candidate that fails its checksum, is cut
short (a byte that cannot belong to it, such as the next sync), is too long, or is still incomplete when
the stream ends is rejected, and the search resumes ONE byte after its start: a stray sync byte or a false
UBX header never costs the valid frames behind it (the trap of the libraries' own stream readers).

What a hostile stream costs stays within a few times a real one's (bench/gnss_framer.py): a long UBX body's
checksum comes from running sums of the stream kept across reads (each byte summed once), not from a walk over
the claimed length for every false header, nor from sums of the whole buffer made again at each read while a
false header waits for its 8 KiB; a run of candidates that fail on sight (a '$' cut short by a byte that cannot
belong to a sentence, a line without a checksum, a UBX header claiming more than UBX_MAX_PAYLOAD) is rejected in
one step, each counted; a sentence's bytes are looked at up to the first that ends it, not over the longest a
sentence may be.

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
_DIRECT_CHECKSUM_BYTES = 128  # a UBX body up to this long is summed directly, a longer one from _RunningSums
_BODY = rb"\x20-\x23\x25-\x7e"  # _NMEA_BODY_BYTES as a regex class
_HEX = rb"0-9A-Fa-f"
# Candidates rejected on sight, one after another, each followed by the bytes skipped up to the next sync (never a
# UBX sync, '$' or '\n', so that within a match each '$' starts one candidate, each UBX sync one UBX header, each
# '\n' ends one line; a 0xB5 only with a byte after it that is not 0x62): a '$' cut short by a byte that cannot
# belong to a sentence (nmea_truncated), a line of body bytes that does not end in *hh (nmea_no_checksum), both
# within 80 bytes (a longer one goes the usual way: the regex looks at no more than that), and a UBX header
# claiming more than UBX_MAX_PAYLOAD (0x2000) bytes (ubx_too_long). Each is what _nmea_candidate / _ubx_candidate
# would say. Possessive: nothing is looked at twice.
_REJECTED_RUN = re.compile(
    rb"(?:(?:\$[%(b)s\r]{0,80}+(?=[^%(b)s\r\n])"
    rb"|\$[%(b)s]{0,80}+(?<!\*[%(h)s]{2})\r?\n"
    rb"|\xb5\x62(?=..(?:.[\x21-\xff]|[\x01-\xff]\x20)))"
    rb"(?:[^$\xb5\n]|\xb5(?=[^\x62]))*+)+" % {b"b": _BODY, b"h": _HEX},
    re.DOTALL,
)


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


class _RunningSums:
    """Running sums (mod 256) of the stream's bytes, kept across reads, so that the UBX checksum of any span of the
    buffer costs the same however long it is, and each byte is summed once however long a false header waits."""

    def __init__(self) -> None:
        self.origin = 0  # the stream offset sums[0] stands at
        self.count = 0  # bytes summed from origin on
        self.sums = np.zeros(4097, dtype=np.uint8)  # sums[i] = sum(stream[origin:origin + i]) mod 256
        self.sums_of_sums = np.zeros(4098, dtype=np.uint8)  # [i] = sum(sums[:i]) mod 256

    def cover(self, buf: bytearray, offset: int) -> None:
        """Sum what `buf` (the stream from `offset` on) holds that is not summed yet."""
        if offset > self.origin + self.count:  # bytes dropped unsummed: start again at the buffer
            self.origin, self.count = offset, 0
        elif offset - self.origin > max(self.count // 2, 4096):  # mostly dropped bytes: move the rest down
            drop = offset - self.origin
            self.count -= drop
            self.sums[: self.count + 1] = self.sums[drop : drop + self.count + 1]
            self.sums_of_sums[: self.count + 2] = self.sums_of_sums[drop : drop + self.count + 2]
            self.origin = offset
        new = buf[self.origin + self.count - offset :]  # a copy: the buffer is resized after the drain
        n, k = self.count, len(new)
        if n + k + 2 > len(self.sums_of_sums):
            size = 2 * (n + k + 2)
            self.sums = np.concatenate([self.sums[: n + 1], np.zeros(size - n - 1, np.uint8)])
            self.sums_of_sums = np.concatenate([self.sums_of_sums[: n + 2], np.zeros(size - n - 2, np.uint8)])
        tail = self.sums[n + 1 : n + 1 + k]
        np.cumsum(np.frombuffer(new, dtype=np.uint8), dtype=np.uint8, out=tail)
        tail += self.sums[n]
        tail_of_sums = self.sums_of_sums[n + 2 : n + 2 + k]
        np.cumsum(tail, dtype=np.uint8, out=tail_of_sums)
        tail_of_sums += self.sums_of_sums[n + 1]
        self.count += k

    def ubx_checksum(self, lo: int, hi: int) -> bytes:
        """ubx_checksum(stream[lo:hi]) (stream offsets, covered): CK_A = the sum of the bytes, CK_B = the sum of
        the running sums."""
        lo, hi = lo - self.origin, hi - self.origin
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
        self._offset = 0  # stream offset of the buffer's first byte
        self._sums = _RunningSums()
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
            self._health.count_rejected(f"framer: {kind}", n)

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
        covered = False  # the running sums reach the buffer's end
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
            run = _REJECTED_RUN.match(buf, start)
            if run:
                self._reject_run(buf, start, run.end())
                pos = run.end()
                continue
            if buf[start] == NMEA_SYNC:
                outcome, end = _nmea_candidate(buf, start, final)
            else:
                outcome, end = _ubx_candidate(buf, start, final)
                if outcome == "check":
                    if end - start - 4 <= _DIRECT_CHECKSUM_BYTES:
                        checksum = ubx_checksum(buf[start + 2 : end - 2])
                    else:
                        if not covered:
                            self._sums.cover(buf, self._offset)
                            covered = True
                        checksum = self._sums.ubx_checksum(self._offset + start + 2, self._offset + end - 2)
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
        self._offset += pos
        return frames

    def _reject_run(self, buf: bytearray, start: int, end: int) -> None:
        """Count the candidates of a _REJECTED_RUN match buf[start:end], and its bytes as skipped."""
        lines = buf.count(b"\n", start, end)
        for kind, n in (("nmea_truncated", buf.count(NMEA_SYNC, start, end) - lines), ("nmea_no_checksum", lines),
                        ("ubx_too_long", buf.count(UBX_SYNC, start, end))):
            if n:
                self._reject(kind, n)
        self.skipped_bytes += end - start
        self._after_rejection = True


def _next_sync(buf: bytearray, pos: int) -> int:
    nmea = buf.find(NMEA_SYNC, pos)
    ubx = buf.find(UBX_SYNC, pos, nmea + 1 if nmea >= 0 else len(buf))
    if ubx >= 0 and (nmea < 0 or ubx < nmea):
        return ubx
    return nmea


def _nmea_candidate(buf: bytearray, start: int, final: bool) -> tuple[str, int]:
    """("frame", end) | ("more", 0) | (rejection kind, 0) for the sentence starting at buf[start] == '$'."""
    limit = min(len(buf), start + NMEA_MAX_BYTES)
    next_sync = buf.find(NMEA_SYNC, start + 1, limit)  # the next '$' ends it: nothing past it is looked at
    end = limit if next_sync < 0 else next_sync
    newline = buf.find(b"\n", start + 1, end)
    if newline < 0:
        if end < limit or buf[start + 1 : end].translate(None, _NMEA_PARTIAL_BYTES):
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
