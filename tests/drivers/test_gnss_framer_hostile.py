"""The framer on the shared real u-blox logs and on hostile streams: every real message framed, every false
candidate rejected and counted by reason, and what a false UBX header costs bounded by work, not by time: the
bytes the per-frame checksum walks stay within a small multiple of the input (it walked each false header's
claimed length, up to 8 KiB, for every 8 bytes of such a stream), the running sums walk each byte once (they were
made again over the whole buffer at each read), and candidates that fail on sight are not looked at one by one
(bench/gnss_framer.py gives the CPU figures)."""

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


class _CountedNumpy:
    """numpy as the framer sees it, counting the bytes its cumulative sums walk."""

    def __init__(self, real):
        self.real, self.summed = real, 0

    def __getattr__(self, name):
        return getattr(self.real, name)

    def cumsum(self, a, *args, **kwargs):
        self.summed += len(a)
        return self.real.cumsum(a, *args, **kwargs)


def counted_work(monkeypatch) -> tuple[dict, _CountedNumpy]:
    """Count the bytes the per-frame checksum walks, the sums' walks, and the candidates looked at one by one."""
    walked = {"checksum_bytes": 0, "candidates": 0}
    direct = stream_framer.ubx_checksum

    def counted_checksum(body):
        walked["checksum_bytes"] += len(body)
        return direct(body)

    def counted_candidate(function):
        def candidate(*args):
            walked["candidates"] += 1
            return function(*args)
        return candidate

    numpy = _CountedNumpy(stream_framer.np)
    monkeypatch.setattr(stream_framer, "np", numpy)
    monkeypatch.setattr(stream_framer, "ubx_checksum", counted_checksum)
    for name in ("_nmea_candidate", "_ubx_candidate"):
        monkeypatch.setattr(stream_framer, name, counted_candidate(getattr(stream_framer, name)))
    return walked, numpy


def repeated(unit: bytes, n: int = 100_000) -> bytes:
    return (unit * (n // len(unit) + 1))[:n]


def test_false_ubx_headers_cost_work_in_proportion_to_the_input(monkeypatch):
    walked, numpy = counted_work(monkeypatch)
    rng = random.Random(18)
    stream = bytearray()
    while len(stream) < 200_000:  # a false header every 8 bytes, claiming up to the most a UBX frame may hold
        length = rng.randrange(0, stream_framer.UBX_MAX_PAYLOAD + 1)
        stream += b"\xb5\x62\x01" + bytes((rng.randrange(256), length & 0xFF, length >> 8)) + rng.randbytes(2)
    frames, framer = framed(bytes(stream))
    assert frames == [] and sum(framer.counts.values()) >= len(stream) // 8 - 1
    assert framer.counts["ubx_bad_checksum"] > 20_000
    assert walked["checksum_bytes"] <= 2 * len(stream)  # the old framer: ~4 KiB for each of 25,000 headers
    assert numpy.summed <= 2 * len(stream)  # the sums and the sums of sums: each byte once


def test_a_false_header_waiting_for_8_kib_at_every_read_costs_each_byte_summed_once(monkeypatch):
    """A header claiming 8191 bytes every 6 bytes: at each read one completes while the next waits, so the buffer
    always holds 8 KiB. The running sums take each byte once (they were made again over the buffer at each read:
    about 250 times the input)."""
    walked, numpy = counted_work(monkeypatch)
    stream = repeated(b"\xb5\x62\x01\x07\xff\x1f")
    frames, framer = framed(stream)
    assert frames == [] and framer.counts["ubx_bad_checksum"] > 15_000
    assert numpy.summed <= 2 * len(stream)
    assert walked["checksum_bytes"] == 0


@pytest.mark.parametrize("unit, kinds", [
    (b"$\n", {"nmea_no_checksum"}),
    (b"$A", {"nmea_truncated"}),
    (b"$\x00", {"nmea_truncated"}),
    (b"$\xb5\x62", {"nmea_truncated", "ubx_too_long"}),
    (b"\xb5$", {"nmea_truncated"}),
    (b"$GPGGA,no checksum\r\n\x00", {"nmea_no_checksum"}),
    (b"\xb5\x62\x01\x07\x00\x20" + b"$A" * 29, {"nmea_truncated", "ubx_bad_checksum"}),
], ids=["dollar-newline", "dollar-A", "dollar-nul", "dollar-ubx-sync", "b5-dollar", "no-checksum", "behind-header"])
def test_candidates_that_fail_on_sight_are_rejected_in_runs_each_counted(monkeypatch, unit, kinds):
    """The shortest candidates one after another (a candidate every 2-3 bytes) cost one Python step each: 11-25 times
    the real logs' CPU per byte (bench/gnss_framer.py). Rejected in runs, they are each still counted by reason, and
    looked at one by one only where a read cuts a run."""
    walked, _ = counted_work(monkeypatch)
    stream = repeated(unit)
    health = HealthCounters("gnss")
    frames, framer = framed(stream, StreamFramer(health))
    reads = -(-len(stream) // READ)
    total = sum(framer.counts.values())
    assert frames == [] and kinds <= set(framer.counts)
    assert sum(framer.counts[k] for k in kinds) >= 0.99 * total  # the others: where the stream begins and ends
    assert total == health.rejected >= stream.count(b"$") + stream.count(b"\xb5\x62") - 1
    assert framer.skipped_bytes == len(stream) and framer.pending_bytes == 0
    assert walked["candidates"] <= 3 * reads  # one by one: one for each '$' or UBX sync (11,000 to 50,000)
