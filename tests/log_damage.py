"""The ways a log file gets damaged on disk, as one generator: bit flips, zeroed 4 KiB blocks, random bytes, cuts,
torn record headers and power cuts (cut anywhere, the last blocks before it zeroed or stale garbage). Used by
tests/daemon/test_log_damage.py and bench/parser_fuzz.py."""

from __future__ import annotations

import random

BLOCK = 4096  # a file system block: what a torn write zeroes or leaves stale


def damaged_log(data: bytes, rng: random.Random) -> bytes:
    """`data` (a log file's bytes) with one to three kinds of damage; never shorter than 9 bytes."""
    out = bytearray(data)
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        kind = rng.randrange(6)
        at = rng.randrange(len(out))
        if kind == 0:
            out[at] ^= 1 << rng.randrange(8)
        elif kind == 1:
            at -= at % BLOCK
            out[at:at + BLOCK] = bytes(len(out[at:at + BLOCK]))
        elif kind == 2:
            n = rng.randrange(1, 64)
            out[at:at + n] = rng.randbytes(len(out[at:at + n]))
        elif kind == 3:
            del out[max(at, 9):]
        elif kind == 4:
            out[at:at + 9] = rng.randbytes(len(out[at:at + 9]))  # a record header
        else:  # a power cut: cut anywhere, the last few blocks before it torn (zeroed or stale garbage)
            del out[max(at, 9):]
            for _ in range(rng.randrange(1, 4)):
                b = max(0, len(out) - rng.randrange(1, 16) * BLOCK)
                b -= b % BLOCK
                out[b:b + BLOCK] = bytes(BLOCK) if rng.random() < 0.5 else rng.randbytes(BLOCK)
                del out[len(data):]  # a torn tail may run past the cut, never past the old end
    return bytes(out)
