"""Masks that a viewer shows in colour: a mono8 PNG of class ids turned into the same image as an 8-bit paletted PNG
(colour type 3) whose palette is the classes' colours (daemon.spine.semantic_classes.CLASS_COLOURS). The pixel data
(IDAT) stay as they are: an 8-bit grey pixel and an 8-bit palette index are the same byte, so nothing is decoded."""

from __future__ import annotations

import struct
import zlib

from daemon.spine.semantic_classes import CLASS_COLOURS

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_GREY, _PALETTE = 0, 3
UNKNOWN_CLASS_COLOUR = bytes([255, 0, 255])
_KEPT = {b"IDAT", b"IEND"}  # the colour-type-specific ancillary chunks (tRNS, sBIT, bKGD) and the others go


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def palette_bytes() -> bytes:
    """256 RGB entries: the class colours, then magenta for every id that is no class (visible, never black)."""
    colours = [bytes(int(v) for v in c) for c in CLASS_COLOURS]
    return b"".join(colours) + UNKNOWN_CLASS_COLOUR * (256 - len(colours))


def coloured_mask_png(png: bytes) -> bytes | None:
    """The paletted PNG of a mono8 PNG mask; None when it is not an 8-bit greyscale PNG."""
    if not png.startswith(PNG_SIGNATURE):
        return None
    out = [PNG_SIGNATURE]
    pos = len(PNG_SIGNATURE)
    while pos + 12 <= len(png):
        length, kind = struct.unpack_from(">I4s", png, pos)
        data = png[pos + 8: pos + 8 + length]
        if len(data) != length:
            return None
        if kind == b"IHDR":
            if length != 13 or data[8] != 8 or data[9] != _GREY:  # bit depth 8, greyscale
                return None
            out += [_chunk(b"IHDR", data[:9] + bytes([_PALETTE]) + data[10:]), _chunk(b"PLTE", palette_bytes())]
        elif kind in _KEPT:
            out.append(png[pos: pos + 12 + length])
        pos += 12 + length
        if kind == b"IEND":
            return b"".join(out)
    return None
