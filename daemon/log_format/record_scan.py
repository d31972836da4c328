"""The careful reading of an MCAP file's bytes: a chunk is taken only when it decompresses to its declared size and
matches its CRC; a summary only when it matches the footer's CRC; a file without a trusted summary is walked record by
record, and past a damaged stretch to the next record that checks out, so a torn block costs only what it touched.

Nothing here raises on bad bytes: what cannot be read is a `DamagedRecord` inside, and a `Damage` tally outside
(stretches skipped, bytes, the first reason). The limits keep a damaged length field from costing memory or time:
every step of the walk moves forward and every read is bounded.
"""

from __future__ import annotations

import io
import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.summary import Summary

MAGIC = b"\x89MCAP0\r\n"
MAX_CHUNK_BYTES = 1 << 30  # a chunk claiming more (stored or decompressed) is damaged: ours are 4 MiB + one message
MAX_RECORD_BYTES = 64 << 20  # any other record (ours are metadata of a few hundred KiB at most)
SCAN_WINDOW = 4 << 20  # bytes searched at a time for the next intact record after damage
FOOTER_BYTES = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc
CHUNK_FIXED = struct.Struct("<QQQII")  # message_start_time, message_end_time, uncompressed_size, crc, len(compression)
MESSAGE_FIXED = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time (then the data)
# Where an intact record may start after damage: a chunk (length < 1 GiB) or a metadata record (< 16 MiB); each
# candidate is then checked in full (a chunk by its CRC), so these only keep the checking rare.
_RESYNC = re.compile(rb"(?=\x06[\x00-\xff]{3}[\x00-\x3f]\x00{4}|\x0c[\x00-\xff]{3}\x00{5})", re.DOTALL)
# Records read with the library's parser from exactly their own bytes (a chunk is parsed here, see read_chunk).
_RECORD_TYPES: dict[int, type] = {
    Opcode.HEADER: Header, Opcode.FOOTER: Footer, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel,
    Opcode.MESSAGE: Message, Opcode.MESSAGE_INDEX: MessageIndex, Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.ATTACHMENT: Attachment, Opcode.ATTACHMENT_INDEX: AttachmentIndex, Opcode.STATISTICS: Statistics,
    Opcode.METADATA: Metadata, Opcode.METADATA_INDEX: MetadataIndex, Opcode.SUMMARY_OFFSET: SummaryOffset,
    Opcode.DATA_END: DataEnd,
}


class DamagedRecord(ValueError):
    """The bytes of one record do not hold what its header says (bad CRC, size, compression, fields)."""


@dataclass
class Damage:
    """What a walk over a file could not read."""

    stretches: int = 0  # damaged stretches skipped (a torn chunk, a bad CRC, garbage), the truncated end excepted
    bytes_skipped: int = 0
    truncated: bool = False  # the file ends inside a record (a writer killed mid-write, the usual power cut)
    first_error: str = ""

    def skip(self, offset: int, length: int, why: str, truncated: bool = False) -> None:
        self.bytes_skipped += length
        if truncated:
            self.truncated = True
        else:
            self.stretches += 1
        if not self.first_error:
            self.first_error = f"{why} at byte {offset}"


def _read_at(f: BinaryIO, offset: int, length: int) -> bytes:
    f.seek(offset)
    return f.read(length)


def parse_record(opcode: int, body: bytes) -> McapRecord:
    """One non-chunk record from exactly its body bytes, all of them used; DamagedRecord otherwise."""
    cls = _RECORD_TYPES.get(opcode)
    if cls is None:
        raise DamagedRecord(f"unknown record opcode 0x{opcode:02x}")
    stream = ReadDataStream(io.BytesIO(body))
    try:  # the library's parsers raise struct.error, EndOfFile, UnicodeDecodeError, ... on bad bytes
        record = cls.read(stream, len(body)) if cls is Message else cls.read(stream)
    except Exception as exc:  # noqa: BLE001 - any failure to parse untrusted bytes is damage
        raise DamagedRecord(f"unreadable {cls.__name__} record ({type(exc).__name__})") from None
    if stream.count != len(body):
        raise DamagedRecord(f"{cls.__name__} record of {len(body)} bytes holds {stream.count}")
    return record


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    """At most `size` + 1 bytes out, whatever the compressed data claims (a damaged size cannot cost memory)."""
    if compression == "":
        return data
    try:
        if compression == "lz4":
            dec = lz4.frame.LZ4FrameDecompressor()
            out = dec.decompress(data, max_length=size + 1)
            if not dec.eof:
                raise DamagedRecord("lz4 chunk does not end where its declared size says")
            return out
        return zstandard.ZstdDecompressor().stream_reader(data).read(size + 1)
    except DamagedRecord:
        raise
    except Exception as exc:  # noqa: BLE001 - lz4 raises RuntimeError, zstandard ZstdError on damaged data
        raise DamagedRecord(f"{compression} chunk does not decompress ({type(exc).__name__})") from None


def read_chunk(f: BinaryIO, offset: int, length: int, strict: bool = False) -> list[McapRecord]:
    """The schemas, channels and messages of the chunk record at `offset` (its body `length` bytes), once its size
    and CRC check out. strict (when looking for an intact record after damage): the CRC must be there and the
    record exactly full."""
    head = _read_at(f, offset + 9, min(length, CHUNK_FIXED.size + 4 + 8))
    if len(head) < CHUNK_FIXED.size:
        raise DamagedRecord("chunk record too short")
    _, _, size, crc, comp_len = CHUNK_FIXED.unpack_from(head)
    at = CHUNK_FIXED.size
    compression = head[at:at + comp_len] if comp_len <= 4 else b"?"
    if compression not in (b"", b"lz4", b"zstd"):
        raise DamagedRecord("chunk with an unknown compression")
    at += comp_len
    if at + 8 > len(head):
        raise DamagedRecord("chunk record too short")
    (data_len,) = struct.unpack_from("<Q", head, at)
    at += 8
    if at + data_len > length or (strict and at + data_len != length):
        raise DamagedRecord("chunk data does not fit its record")
    if size > MAX_CHUNK_BYTES:
        raise DamagedRecord(f"chunk claims {size} bytes uncompressed")
    if strict and crc == 0:
        raise DamagedRecord("chunk without a CRC")
    stored = _read_at(f, offset + 9 + at, data_len)
    if len(stored) != data_len:
        raise DamagedRecord("chunk cut off by the end of the file")
    data = _decompress(compression.decode(), stored, size)
    if len(data) != size:
        raise DamagedRecord(f"chunk decompresses to {len(data)} bytes, not its declared {size}")
    if crc and zlib.crc32(data) != crc:
        raise DamagedRecord("chunk CRC mismatch")
    records: list[McapRecord] = []
    pos = 0
    while pos < len(data):
        if pos + 9 > len(data):
            raise DamagedRecord("chunk ends inside a record header")
        opcode, record_length = struct.unpack_from("<BQ", data, pos)
        end = pos + 9 + record_length
        if end > len(data):
            raise DamagedRecord("record runs past the end of its chunk")
        if opcode == Opcode.MESSAGE:  # the bulk of every chunk: parsed here, without the library's stream
            if record_length < MESSAGE_FIXED.size:
                raise DamagedRecord("message record too short")
            channel_id, sequence, log_time, publish_time = MESSAGE_FIXED.unpack_from(data, pos + 9)
            records.append(Message(channel_id=channel_id, sequence=sequence, log_time=log_time,
                                   publish_time=publish_time, data=data[pos + 9 + MESSAGE_FIXED.size:end]))
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            records.append(parse_record(opcode, data[pos + 9:end]))
        pos = end  # other records inside a chunk are skipped, as the MCAP spec says
    return records


def _record_at(f: BinaryIO, offset: int, opcode: int, length: int, strict: bool = False) -> list[McapRecord]:
    """The records of the top-level record at `offset`: a chunk's contents, or the record itself."""
    if opcode == Opcode.CHUNK:
        return read_chunk(f, offset, length, strict)
    return [parse_record(opcode, _read_at(f, offset + 9, length))]


def _checked_at(f: BinaryIO, offset: int, size: int) -> bool:
    """Whether an intact chunk or roadlog metadata record starts at `offset` (after damage: so the walk resumes)."""
    head = _read_at(f, offset, 9 + CHUNK_FIXED.size + 4 + 8)
    if len(head) < 9:
        return False
    opcode, length = struct.unpack_from("<BQ", head)
    if offset + 9 + length > size:
        return False
    if opcode == Opcode.CHUNK:
        if len(head) < 9 + CHUNK_FIXED.size:
            return False
        _, _, usize, crc, comp_len = CHUNK_FIXED.unpack_from(head, 9)
        at = 9 + CHUNK_FIXED.size
        if crc == 0 or usize > MAX_CHUNK_BYTES or length > MAX_CHUNK_BYTES or comp_len > 4 or \
                head[at:at + comp_len] not in (b"", b"lz4", b"zstd") or len(head) < at + comp_len + 8:
            return False
        if struct.unpack_from("<Q", head, at + comp_len)[0] != length - CHUNK_FIXED.size - comp_len - 8:
            return False
    elif length > MAX_RECORD_BYTES:
        return False
    try:
        records = _record_at(f, offset, opcode, length, strict=True)
    except DamagedRecord:
        return False
    return opcode == Opcode.CHUNK or records[0].name.startswith("roadlog")


def resync(f: BinaryIO, start: int, size: int) -> int | None:
    """The offset of the next intact chunk or roadlog metadata record at or after `start`, None when there is none."""
    window = start
    while window < size:
        buf = _read_at(f, window, SCAN_WINDOW + 16)
        for m in _RESYNC.finditer(buf):
            if m.start() >= SCAN_WINDOW:
                break  # the next window looks at it
            if _checked_at(f, window + m.start(), size):
                return window + m.start()
        window += SCAN_WINDOW
    return None


def scan_records(f: BinaryIO, size: int, damage: Damage, chunks: bool = True) -> Iterator[McapRecord]:
    """Every intact record of the data section, in file order (a chunk's schemas, channels and messages in its
    place), skipping damaged stretches; stops at the DataEnd record (the summary after it only repeats).
    chunks=False: chunks are stepped over unread (looking for metadata)."""
    pos: int | None = len(MAGIC)
    if _read_at(f, 0, len(MAGIC)) != MAGIC:
        pos = resync(f, 0, size)
        damage.skip(0, size if pos is None else pos, "no MCAP magic")
    while pos is not None and pos < size:
        header = _read_at(f, pos, 9)
        problem, truncated, records = "", False, []
        if len(header) < 9:
            problem, truncated = "file ends inside a record header", True
        else:
            opcode, length = struct.unpack("<BQ", header)
            if opcode != Opcode.CHUNK and opcode not in _RECORD_TYPES:
                problem = f"unknown record opcode 0x{opcode:02x}"
            elif length > (MAX_CHUNK_BYTES if opcode == Opcode.CHUNK else MAX_RECORD_BYTES):
                problem = f"record of {length} bytes"
            elif pos + 9 + length > size:
                problem, truncated = "file ends inside a record", True
            elif chunks or opcode != Opcode.CHUNK:
                try:
                    records = _record_at(f, pos, opcode, length)
                except DamagedRecord as exc:
                    problem = str(exc)
        if problem:
            resume = resync(f, pos + 1, size)
            damage.skip(pos, (size if resume is None else resume) - pos, problem, truncated and resume is None)
            pos = resume
            continue
        yield from records
        if opcode in (Opcode.DATA_END, Opcode.FOOTER):
            return
        pos += 9 + length


def trusted_summary(f: BinaryIO, size: int) -> tuple[Summary | None, str]:
    """The file's summary when its footer is intact and the summary matches the footer's CRC (the chunk index can
    then be followed), else None and why not ("" for a file that simply has no footer: it was never closed)."""
    if size < 2 * len(MAGIC) + FOOTER_BYTES:
        return None, ""
    tail = _read_at(f, size - FOOTER_BYTES - len(MAGIC), FOOTER_BYTES + len(MAGIC))
    if tail[-len(MAGIC):] != MAGIC or tail[0] != Opcode.FOOTER:
        return None, ""
    (length, summary_start, _, crc) = struct.unpack_from("<QQQI", tail, 1)
    footer_at = size - FOOTER_BYTES - len(MAGIC)
    if length != 20 or summary_start == 0 or not len(MAGIC) <= summary_start <= footer_at:
        return None, "footer damaged"
    summary_bytes = _read_at(f, summary_start, footer_at - summary_start)
    if crc and zlib.crc32(tail[:1 + 8 + 8 + 8], zlib.crc32(summary_bytes)) != crc:
        return None, "summary CRC mismatch"
    summary = Summary()
    pos = 0
    try:
        while pos < len(summary_bytes):
            opcode, length = struct.unpack_from("<BQ", summary_bytes, pos)
            record = parse_record(opcode, summary_bytes[pos + 9:pos + 9 + length])
            pos += 9 + length
            if isinstance(record, Schema):
                summary.schemas[record.id] = record
            elif isinstance(record, Channel):
                summary.channels[record.id] = record
            elif isinstance(record, ChunkIndex):
                summary.chunk_indexes.append(record)
            elif isinstance(record, MetadataIndex):
                summary.metadata_indexes.append(record)
            elif isinstance(record, Statistics):
                summary.statistics = record
    except (DamagedRecord, struct.error):
        return None, "summary unreadable"
    if any(c.chunk_start_offset + c.chunk_length > summary_start for c in summary.chunk_indexes) or any(
            m.offset + m.length > summary_start for m in summary.metadata_indexes):
        return None, "summary points past the data section"
    return summary, ""


def check_closed_file(f: BinaryIO, summary: Summary, damage: Damage) -> None:
    """What a closed file's chunk index does not cover: its leading magic and the metadata records the summary
    points at (they carry no CRC of their own: each must at least parse)."""
    if _read_at(f, 0, len(MAGIC)) != MAGIC:
        damage.skip(0, len(MAGIC), "no MCAP magic")
    for index in summary.metadata_indexes:
        try:
            if not isinstance(read_record_at(f, index.offset, index.length), Metadata):
                raise DamagedRecord("not a metadata record")
        except DamagedRecord as exc:
            damage.skip(index.offset, index.length, f"metadata record {index.name!r}: {exc}")


def read_chunk_at(f: BinaryIO, offset: int, length: int) -> list[McapRecord]:
    """The records of the chunk the summary's index puts at `offset` (DamagedRecord when it does not check out)."""
    header = _read_at(f, offset, 9)
    if length < 9 or len(header) != 9 or header[0] != Opcode.CHUNK or struct.unpack_from("<Q", header, 1)[0] != \
            length - 9:
        raise DamagedRecord("chunk index does not point at a chunk")
    return read_chunk(f, offset, length - 9)


def read_record_at(f: BinaryIO, offset: int, length: int) -> McapRecord:
    """The non-chunk record the summary's index puts at `offset` (DamagedRecord when it does not check out)."""
    raw = _read_at(f, offset, length)
    if len(raw) != length or length < 9 or struct.unpack_from("<Q", raw, 1)[0] != length - 9:
        raise DamagedRecord("index does not point at a record")
    return parse_record(raw[0], raw[9:])
