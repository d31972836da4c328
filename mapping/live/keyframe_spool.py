"""The mapping worker's disk spool: every bus message it needs, kept on disk until no window needs it.

Messages are appended, as the bus carries them (protobuf meta + bulk bytes, `daemon.spine.message_codec`), to
chunk files of `chunk_s` seconds of arrival time: `chunk-000042.bin`. A record is a fixed header
(topic length, meta length, bulk length, arrival ns) then the topic name, meta and bulk. A chunk torn by
a crash ends in a partial record, which reading stops at. Whole chunks are deleted once every window
that could use them is finished (`prune_before`); the in-memory index holds only each chunk's time
span and size, so the spool costs no memory with the drive's length.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from daemon.spine import message_codec
from daemon.spine.topics import Topic

_HEADER = struct.Struct("<HIIq")  # topic length, meta length, bulk length, arrival host ns


@dataclass
class SpoolChunk:
    index: int
    path: Path
    first_ns: int
    last_ns: int
    bytes: int


@dataclass
class KeyframeSpool:
    """Append-only chunk files of bus messages under `folder`."""

    folder: Path
    topics: dict[str, Topic]
    chunk_s: float = 10.0
    chunks: list[SpoolChunk] = field(default_factory=list)
    torn_records: int = 0  # partial records found at the end of chunks (crash)
    _file: object = None

    def __post_init__(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        for path in sorted(self.folder.glob("chunk-*.bin")):
            first = last = None
            for arrival, _, _, _ in self._records(path):
                first = arrival if first is None else min(first, arrival)
                last = arrival if last is None else max(last, arrival)
            if first is None:
                path.unlink()
                continue
            self.chunks.append(SpoolChunk(int(path.stem.split("-")[1]), path, first, last, path.stat().st_size))

    @property
    def bytes(self) -> int:
        return sum(c.bytes for c in self.chunks)

    def append(self, topic: str, message: object, arrival_ns: int) -> None:
        meta, bulk = message_codec.encode_split(message)
        name = topic.encode()
        chunk = self.chunks[-1] if self.chunks and self._file is not None else None
        if chunk is None or arrival_ns - chunk.first_ns > self.chunk_s * 1e9:
            self.flush_close()
            index = self.chunks[-1].index + 1 if self.chunks else 0
            path = self.folder / f"chunk-{index:06d}.bin"
            self._file = open(path, "ab")
            chunk = SpoolChunk(index, path, arrival_ns, arrival_ns, 0)
            self.chunks.append(chunk)
        record = _HEADER.pack(len(name), len(meta), len(bulk), arrival_ns) + name + bytes(meta)
        self._file.write(record)
        self._file.write(bulk)
        chunk.first_ns = min(chunk.first_ns, arrival_ns)  # topics are read in turns: arrivals interleave
        chunk.last_ns = max(chunk.last_ns, arrival_ns)
        chunk.bytes += len(record) + len(bulk)

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def flush_close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def _records(self, path: Path) -> Iterator[tuple[int, str, bytes, bytes]]:
        with open(path, "rb") as f:
            data = f.read()
        pos = 0
        while pos < len(data):
            if pos + _HEADER.size > len(data):
                self.torn_records += 1
                return
            nt, nm, nb, arrival = _HEADER.unpack_from(data, pos)
            end = pos + _HEADER.size + nt + nm + nb
            if end > len(data):
                self.torn_records += 1
                return
            p = pos + _HEADER.size
            yield arrival, data[p:p + nt].decode(), data[p + nt:p + nt + nm], data[p + nt + nm:end]
            pos = end

    def read(self, first_ns: int, last_ns: int, topics: set[str]) -> Iterator[tuple[int, str, object]]:
        """(arrival ns, topic, message) of the given topics that arrived in [first_ns, last_ns], in spool order."""
        self.flush()
        for chunk in list(self.chunks):
            if chunk.last_ns < first_ns or chunk.first_ns > last_ns:
                continue
            for arrival, topic, meta, bulk in self._records(chunk.path):
                if topic in topics and first_ns <= arrival <= last_ns:
                    yield arrival, topic, message_codec.decode_split(self.topics[topic].message_type, meta, bulk)

    def last_seq_and_newest(self) -> tuple[dict[str, int], dict[str, int]]:
        """Last seq and newest host time per topic already spooled (a restart skips those when the bus still
        holds them, and knows how far each topic's data reaches)."""
        last: dict[str, int] = {}
        newest: dict[str, int] = {}
        for chunk in self.chunks:
            for arrival, topic, msg in self.read(chunk.first_ns, chunk.last_ns, set(self.topics)):
                last[topic] = max(last.get(topic, -1), msg.seq)
                newest[topic] = max(newest.get(topic, arrival), arrival)
        return last, newest

    def prune_before(self, ns: int) -> int:
        """Delete the closed chunks that end before `ns`; returns the bytes freed."""
        freed = 0
        keep = []
        for i, chunk in enumerate(self.chunks):
            is_open = self._file is not None and i == len(self.chunks) - 1
            if chunk.last_ns < ns and not is_open:
                freed += chunk.bytes
                os.unlink(chunk.path)
            else:
                keep.append(chunk)
        self.chunks = keep
        return freed
