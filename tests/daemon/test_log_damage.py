"""Damaged logs, read through read_log, recover_log and `roadlog log-info`: a torn 4 KiB block (a power cut's torn
write) in an unclosed segment costs exactly the chunks it touched; a flipped bit in a closed segment is caught by the
chunk's CRC and the file is reported damaged; no damage ever raises. The recorder and replay on such files are in
test_recorder.py and test_replay.py."""

from __future__ import annotations

import json
import random
import struct
import subprocess
import sys
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from daemon.log_format.metadata_records import log_time_offset
from daemon.log_format.reader import ReadReport, read_log, read_metadata
from daemon.log_format.recovery import recover_log
from daemon.log_format.writer import LogWriter
from tests.daemon.test_log_format import CONFIG, _messages
from tests.log_damage import BLOCK, damaged_log

ROOT = Path(__file__).resolve().parents[2]


def second_lz4_block_header(data: bytes) -> int:
    """Where the size of the second block of the file's first lz4 frame (the first chunk's) is stored."""
    at = data.index(bytes.fromhex("04224d18"))  # the lz4 frame magic
    at += 4 + 2 + (8 if data[at + 4] & 0x08 else 0) + 1  # FLG, BD, content size, header checksum
    return at + 4 + (struct.unpack_from("<I", data, at)[0] & 0x7FFFFFFF)  # the high bit marks a stored block


def write_open_and_closed(tmp_path: Path, n_rounds: int = 40, compression: str = "lz4") -> tuple[bytes, Path, dict]:
    """The same log as an unclosed segment's bytes (what a killed writer leaves: its written chunks, no footer) and
    as a closed file; the original messages by (topic, log time)."""
    msgs = _messages(n_rounds)
    closed = tmp_path / "closed.mcap"
    writer = LogWriter(closed, CONFIG, chunk_size=16 * 1024, compression=compression)
    for topic, msg in msgs:
        writer.write(topic, msg)
    writer.flush()
    open_bytes = closed.read_bytes()
    writer.close()
    return open_bytes, closed, {(t, m.host_mono_ns): m for t, m in msgs}


def chunk_spans(closed: Path) -> list[tuple[int, int, set]]:
    """(start, end, {(topic, host time)}) of every chunk of a closed file, from the mcap library's own index (its UTC
    log times moved back by each channel's offset, as read_log gives them)."""
    with open(closed, "rb") as f:
        summary = make_reader(f).get_summary()
        spans = []
        for index in summary.chunk_indexes:
            f.seek(index.chunk_start_offset + 9)
            records = breakup_chunk(Chunk.read(ReadDataStream(f)), validate_crc=True)
            keys = {(summary.channels[r.channel_id].topic,
                     r.log_time - log_time_offset(summary.channels[r.channel_id].metadata))
                    for r in records if isinstance(r, Message)}
            spans.append((index.chunk_start_offset, index.chunk_start_offset + index.chunk_length, keys))
    return spans


def messages_in(spans: list[tuple[int, int, set]], length: int) -> set:
    """The (topic, log time) of the messages in the chunks that lie within the first `length` bytes."""
    keys = set().union(*(keys for _, end, keys in spans if end <= length))
    return {k for k in keys if not k[0].startswith(("calibration/", "tf_static", "mask_colour/"))}  # views only


def read_back(path: Path) -> tuple[dict, ReadReport]:
    report = ReadReport()
    got = {(r.topic, r.log_time_ns): r.message for r in read_log([path], report=report)}
    return got, report


def test_a_torn_block_in_an_unclosed_segment_costs_only_the_chunks_it_touched(tmp_path):
    open_bytes, closed, originals = write_open_and_closed(tmp_path)
    spans = [s for s in chunk_spans(closed) if s[1] <= len(open_bytes)]
    in_open = messages_in(spans, len(open_bytes))
    rng = random.Random(11)
    offsets = sorted({0, spans[0][0], spans[0][0] + 100, len(open_bytes) - BLOCK // 2}
                     | {rng.randrange(0, len(open_bytes)) for _ in range(40)})
    path = tmp_path / "seg.mcap.open"
    for offset in offsets:
        torn = bytearray(open_bytes)
        torn[offset:offset + BLOCK] = bytes(len(torn[offset:offset + BLOCK]))
        path.write_bytes(torn)
        got, report = read_back(path)
        lost = set().union(*(keys for start, end, keys in spans if start < offset + BLOCK and offset < end))
        assert set(got) == in_open - lost, offset  # every intact chunk, nothing from a torn one
        assert all(got[k] == originals[k] for k in got)
        fr = report.files[0]
        assert not fr.complete and fr.bytes_skipped >= (BLOCK if offset + BLOCK <= len(open_bytes) else 1)
        if lost:
            assert fr.damaged_chunks >= 1 and fr.error, offset


def test_recovery_of_a_torn_segment_keeps_every_intact_chunk_and_its_metadata(tmp_path):
    open_bytes, closed, originals = write_open_and_closed(tmp_path)
    spans = chunk_spans(closed)
    torn = bytearray(open_bytes)
    middle = spans[len(spans) // 2]
    torn[middle[0] + 64:middle[0] + 64 + BLOCK] = bytes(BLOCK)
    src = tmp_path / "seg.mcap.open"
    src.write_bytes(torn)
    kept = recover_log(src, tmp_path / "fixed.mcap", CONFIG)
    assert kept.damaged_chunks == 1 and ("CRC" in kept.error or "decompress" in kept.error), kept.error
    got, report = read_back(tmp_path / "fixed.mcap")
    assert report.files[0].complete and len(got) == kept.messages
    assert set(got) == messages_in(spans, len(open_bytes)) - middle[2]
    assert all(got[k] == originals[k] for k in got)
    assert read_metadata(tmp_path / "fixed.mcap")["roadlog"]["recovered_from"] == str(src)


def test_a_flipped_bit_in_a_closed_segment_fails_its_chunk_crc(tmp_path):
    """A bit flipped in a chunk's stored bytes (lz4 keeps incompressible payloads as literals, so it still
    decompresses): that chunk's messages are left out and the file is reported damaged, not complete."""
    _, closed, originals = write_open_and_closed(tmp_path)
    spans = chunk_spans(closed)
    start, end, keys = spans[3]
    data = bytearray(closed.read_bytes())
    data[(start + end) // 2] ^= 0x10
    flipped = tmp_path / "flipped.mcap"
    flipped.write_bytes(data)
    got, report = read_back(flipped)
    fr = report.files[0]
    assert not fr.complete and fr.damaged_chunks == 1 and "CRC mismatch" in fr.error
    assert set(got) == {k for k in originals if k not in keys}
    assert all(got[k] == originals[k] for k in got)


def test_a_damaged_summary_is_not_trusted_and_every_chunk_is_still_read(tmp_path):
    _, closed, originals = write_open_and_closed(tmp_path)
    with open(closed, "rb") as f:
        summary_start = make_reader(f).get_summary().chunk_indexes[-1].chunk_start_offset
    data = bytearray(closed.read_bytes())
    data[len(data) - 200] ^= 0x01  # in the summary section (chunk index, statistics, ...)
    assert summary_start < len(data) - 200
    damaged = tmp_path / "summary.mcap"
    damaged.write_bytes(data)
    got, report = read_back(damaged)
    assert not report.files[0].complete and "summary" in report.files[0].error
    assert got == {k: m for k, m in originals.items()}


def test_fuzzed_damage_never_raises_never_returns_a_corrupt_message_and_never_hides_a_loss(tmp_path):
    """200 damaged closed and unclosed files (zstd and lz4): read_log and recover_log never raise; every message
    read is one that was written; when messages are missing the file is reported incomplete; the recovered file
    reads back complete with what was recovered. (bench/parser_fuzz.py runs thousands, of the same damage.)"""
    rng = random.Random(2026)
    cases = []
    for compression in ("lz4", "zstd"):
        open_bytes, closed, originals = write_open_and_closed(tmp_path, n_rounds=12, compression=compression)
        cases += [(closed.read_bytes(), originals), (open_bytes, originals)]
    path, fixed = tmp_path / "fuzzed.mcap", tmp_path / "fixed.mcap"
    for i in range(200):
        data, originals = cases[i % len(cases)]
        path.write_bytes(damaged_log(data, rng))
        got, report = read_back(path)
        assert all(k in originals and originals[k] == m for k, m in got.items()), i
        if len(got) < len(originals) and report.files[0].complete:
            raise AssertionError(f"case {i}: {len(originals) - len(got)} messages lost in a file reported complete")
        kept = recover_log(path, fixed, CONFIG)
        again, fixed_report = read_back(fixed)
        assert fixed_report.files[0].complete and again == got and kept.messages == len(got), i


def test_log_info_reports_a_damaged_segment_instead_of_a_traceback(tmp_path):
    open_bytes, closed, originals = write_open_and_closed(tmp_path)
    spans = chunk_spans(closed)
    torn = bytearray(open_bytes)
    torn[spans[2][0] + 200:spans[2][0] + 200 + BLOCK] = bytes(BLOCK)
    path = tmp_path / "seg.mcap.open"
    path.write_bytes(torn)
    done = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "log-info", str(path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    info = json.loads(done.stdout)["files"][0]
    assert not info["complete"] and info["damaged_chunks"] == 1 and info["error"]
    assert info["messages"] == len(messages_in(spans, len(open_bytes)) - spans[2][2])
    assert "damaged log" in done.stderr


def test_log_info_reads_a_segment_whose_first_block_was_torn(tmp_path):
    """Without its magic the file was "not an MCAP file" (exit 1); its chunks are intact, so it is a damaged log."""
    open_bytes, closed, _ = write_open_and_closed(tmp_path)
    torn = bytearray(open_bytes)
    torn[:BLOCK] = bytes(BLOCK)
    path = tmp_path / "seg.mcap.open"
    path.write_bytes(torn)
    done = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "log-info", str(path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    info = json.loads(done.stdout)["files"][0]
    lost = {k for start, _, keys in chunk_spans(closed) if start < BLOCK for k in keys}
    assert not info["complete"] and "no MCAP magic" in info["error"]
    assert info["messages"] == len(messages_in(chunk_spans(closed), len(open_bytes)) - lost)
    (tmp_path / "text.mcap").write_text("hello")
    done = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "log-info", str(tmp_path / "text.mcap")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "is not an MCAP file" in done.stderr
