"""The framer on the shared real u-blox logs and on hostile streams: every real message framed, every false
candidate rejected and counted by reason, and what a false UBX header costs bounded by work, not by time: the
bytes the per-frame checksum walks stay within a small multiple of the input (it walked each false header's
claimed length, up to 8 KiB, for every 8 bytes of such a stream), and the buffer's prefix sums are made at most
once per read (bench/gnss_framer.py gives the CPU figures)."""

from __future__ import annotations

import io
import random
from pathlib import Path

import pytest
from pyubx2 import NMEA_PROTOCOL, UBX_PROTOCOL, UBXReader

from daemon.spine.health import HealthCounters
from drivers.gnss import stream_framer
from drivers.gnss.stream_framer import StreamFramer, ubx_checksum

DATA = Path("/work/shared/data/gnss_pyubx2")
LOGS = sorted(p for p in DATA.glob("*") if p.suffix in (".ubx", ".log")) if DATA.is_dir() else []
READ = 64  # bytes per read, as the serial driver gets them at 460800 baud


def framed(data: bytes, framer: StreamFramer | None = None) -> tuple[list[bytes], StreamFramer]:
    framer = framer or StreamFramer()
    frames = []
    for i in range(0, len(data), READ):
        frames += framer.feed(data[i:i + READ])
    return [f.data for f in frames + framer.flush()], framer


def reference_messages(data: bytes) -> list[bytes]:
    """pyubx2's own reading of the stream: each NMEA sentence (no line end) and UBX frame it parses."""
    reader = UBXReader(io.BytesIO(data), protfilter=NMEA_PROTOCOL | UBX_PROTOCOL, quitonerror=0, validate=1)
    return [raw.rstrip(b"\r\n") if raw[:1] == b"$" else raw for raw, _ in reader]


def in_order(wanted: list[bytes], got: list[bytes]) -> bool:
    it = iter(got)
    return all(any(g == w for g in it) for w in wanted)


@pytest.mark.skipif(not LOGS, reason="shared pyubx2 logs not present")
@pytest.mark.parametrize("log", LOGS, ids=lambda p: p.name)
def test_every_real_message_of_the_shared_logs_is_framed(log):
    data = log.read_bytes()
    reference = reference_messages(data)
    frames, framer = framed(data)
    assert reference and in_order(reference, frames)
    for extra in (f for f in frames if f not in set(reference)):  # pyubx2 skips some it cannot parse: still UBX
        assert extra[:2] == b"\xb5\x62" and ubx_checksum(extra[2:-2]) == extra[-2:]
    assert framer.frame_bytes + framer.skipped_bytes == len(data) and framer.pending_bytes == 0


@pytest.mark.skipif(not LOGS, reason="shared pyubx2 logs not present")
def test_hostile_bytes_between_real_messages_are_rejected_by_reason_and_cost_no_frame():
    messages = reference_messages((DATA / "pygpsdata-MIXED.log").read_bytes())
    rng = random.Random(10)
    false_header = b"\xb5\x62\x01\x07\xd0\x07"  # NAV-PVT claiming 2000 bytes: the messages behind it wait, then go
    hostile = {
        b"$$$$": {"nmea_truncated": 4},  # each '$' cut short by the next sync
        b"\xb5\x62\x01\x02\xff\xff": {"ubx_too_long": 1},
        b"$GPGGA,bad*00\r\n": {"nmea_bad_checksum": 1},
        b"$GPTXT,no checksum\r\n": {"nmea_no_checksum": 1},
        b"noise without a sync": {"garbage": 1},
        false_header: {"ubx_bad_checksum": 1},
    }
    stream, expected = bytearray(), {}
    for i, message in enumerate(messages):
        stream += message + (b"\r\n" if message[:1] == b"$" else b"")
        if i % 3 == 0 and i < len(messages) - 40:  # the false header's 2000 bytes end inside the stream
            junk = rng.choice(sorted(hostile))
            stream += junk
            for kind, n in hostile[junk].items():
                expected[kind] = expected.get(kind, 0) + n
    health = HealthCounters("gnss")
    frames, framer = framed(bytes(stream), StreamFramer(health))
    assert frames == messages
    assert dict(framer.counts) == expected and health.rejected == sum(expected.values())


def test_false_ubx_headers_cost_work_in_proportion_to_the_input(monkeypatch):
    walked = {"checksum_bytes": 0, "prefix_sums": 0}
    direct, prefix = stream_framer.ubx_checksum, getattr(stream_framer, "_PrefixSums", None)

    def counted_checksum(body):
        walked["checksum_bytes"] += len(body)
        return direct(body)

    def counted_prefix_sums(buf):
        walked["prefix_sums"] += 1
        return prefix(buf)

    monkeypatch.setattr(stream_framer, "ubx_checksum", counted_checksum)
    monkeypatch.setattr(stream_framer, "_PrefixSums", counted_prefix_sums, raising=False)
    rng = random.Random(18)
    stream = bytearray()
    while len(stream) < 200_000:  # a false header every 8 bytes, claiming up to the most a UBX frame may hold
        length = rng.randrange(0, stream_framer.UBX_MAX_PAYLOAD + 1)
        stream += b"\xb5\x62\x01" + bytes((rng.randrange(256), length & 0xFF, length >> 8)) + rng.randbytes(2)
    frames, framer = framed(bytes(stream))
    reads = -(-len(stream) // READ) + 1
    assert frames == [] and sum(framer.counts.values()) >= len(stream) // 8 - 1
    assert framer.counts["ubx_bad_checksum"] > 20_000
    assert walked["checksum_bytes"] <= 2 * len(stream)  # the old framer: ~4 KiB for each of 25,000 headers
    assert walked["prefix_sums"] <= reads
