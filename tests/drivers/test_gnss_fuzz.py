"""Hypothesis fuzzing of framer + decoder: random bytes, mutated real streams, checksum-valid nonsense.

Properties: nothing raises; every byte is either in a delivered frame or counted as skipped; skipped
bytes always come with a counted rejection; every frame the mutations did not touch still arrives;
whatever the decoder publishes is well formed.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.spine.health import HealthCounters
from daemon.spine.messages import GnssFix, GnssVelocity, ImuSample
from drivers.gnss.epoch_velocity import MAX_VELOCITY_MPS
from drivers.gnss.gnss_messages import NMEA_WANTED, UBX_WANTED, GnssDecoder
from drivers.gnss.stream_framer import Frame, StreamFramer, nmea_checksum, ubx_checksum

DATA = Path("/work/shared/data")
FUZZ = settings(max_examples=100, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _real_stream() -> bytes:
    """A mixed NMEA + UBX stream: ZED-F9P (RAWX, NMEA), ZED-F9R (NAV-PVAT, ESF), ESF-MEAS and HNR samples."""
    if not DATA.is_dir():
        return b""
    parts = [DATA / "gnss_gpsd/ublox-zed-f9p_hpg1.11.log", DATA / "gnss_pyubx2/pygpsdata-SF-calibration.log",
             DATA / "gnss_pyubx2/pygpsdata-ESF.log", DATA / "gnss_pyubx2/pygpsdata-HNR.log"]
    clean = b""
    for path in parts:
        data = path.read_bytes()[:6_000]
        framer = StreamFramer()
        for frame in framer.feed(data) + framer.flush():  # keep whole frames only: the clean reference
            clean += frame.data + (b"\r\n" if frame.protocol == "nmea" else b"")
    return clean


REAL = _real_stream()


def _frame_spans(stream: bytes) -> list[tuple[int, int]]:
    framer = StreamFramer()
    spans, pos = [], 0
    for frame in framer.feed(stream) + framer.flush():
        start = stream.index(frame.data, pos)
        end = start + len(frame.data) + (2 if frame.protocol == "nmea" else 0)
        spans.append((start, end))
        pos = end
    return spans


SPANS = _frame_spans(REAL) if REAL else []


def run(stream: bytes, cuts: list[int]) -> tuple[list[Frame], StreamFramer, list, HealthCounters]:
    health = HealthCounters("gnss")
    framer, decoder = StreamFramer(health), GnssDecoder(health=health)
    frames, published = [], []
    bounds = sorted({0, len(stream), *(c % (len(stream) + 1) for c in cuts)})
    for a, b in zip(bounds, bounds[1:], strict=False):
        for frame in framer.feed(stream[a:b]):
            frames.append(frame)
            published += decoder.decode(frame, 1)
    for frame in framer.flush():
        frames.append(frame)
        published += decoder.decode(frame, 1)
    published += decoder.flush()
    return frames, framer, published, health


def check_accounting(stream: bytes, framer: StreamFramer, frames: list[Frame]) -> None:
    assert framer.pending_bytes == 0
    assert framer.frame_bytes + framer.skipped_bytes == len(stream)
    if framer.skipped_bytes:
        assert sum(framer.counts.values()) >= 1
    for frame in frames:
        if frame.protocol == "ubx":
            assert ubx_checksum(frame.data[2:-2]) == frame.data[-2:]
        else:
            assert nmea_checksum(frame.data[1:-3]) == int(frame.data[-2:], 16)


def check_published(published: list) -> None:
    for m in published:
        if isinstance(m, GnssFix):
            assert abs(m.latitude_deg) <= 90 and abs(m.longitude_deg) <= 180 and math.isfinite(m.altitude_m)
            assert all(math.isfinite(v) for v in m.position_covariance)
            assert m.position_covariance[0] >= 0 and m.position_covariance[4] >= 0
        elif isinstance(m, GnssVelocity):
            assert all(math.isfinite(v) and abs(v) <= MAX_VELOCITY_MPS for v in m.velocity_enu_mps)
            assert all(math.isfinite(v) for v in m.velocity_covariance) and m.velocity_covariance[0] >= 0
        else:
            assert isinstance(m, ImuSample)
            assert all(math.isfinite(v) for v in m.accel_mps2 + m.gyro_rps)


@FUZZ
@given(st.binary(max_size=3000), st.lists(st.integers(min_value=0, max_value=3000), max_size=8))
def test_random_bytes(data, cuts):
    frames, framer, published, health = run(data, cuts)
    check_accounting(data, framer, frames)
    check_published(published)
    assert health.rejected >= sum(framer.counts.values())


SYNC_BYTES = st.sampled_from([b"$", b"\xb5", b"\xb5b", b"\r\n", b"*", b"\x00", b"\xff"])


@pytest.mark.skipif(not REAL, reason="shared sensor recordings not present")
@FUZZ
@given(st.lists(st.tuples(st.integers(min_value=0, max_value=max(len(REAL) - 1, 0)),
                          st.sampled_from(["flip", "insert", "delete"]),
                          st.integers(min_value=1, max_value=40),
                          SYNC_BYTES | st.binary(min_size=1, max_size=12)), min_size=1, max_size=12),
       st.lists(st.integers(min_value=0, max_value=len(REAL)), max_size=12))
def test_mutated_real_streams_keep_every_untouched_frame(mutations, cuts):
    # apply the mutations in stream order, remembering which original bytes they touch
    stream, touched, pos = bytearray(), [], 0
    for at, kind, n, blob in sorted(mutations):
        if at < pos:
            continue
        stream += REAL[pos:at]
        if kind == "flip":
            stream += bytes(b ^ 0x5A for b in REAL[at:at + n])
            touched.append((at, at + n))
            pos = at + n
        elif kind == "delete":
            touched.append((at, at + n))
            pos = at + n
        else:
            stream += blob
            touched.append((at, at))  # inserted before REAL[at]
            pos = at
    stream += REAL[pos:]
    frames, framer, published, _ = run(bytes(stream), cuts)
    check_accounting(bytes(stream), framer, frames)
    check_published(published)

    def intact(span: tuple[int, int]) -> bool:
        return all(not (a < span[1] and b > span[0]) and not (span[0] < a < span[1]) for a, b in touched)

    expected = [REAL[s:e] for s, e in SPANS if intact((s, e))]
    delivered = iter(f.data + (b"\r\n" if f.protocol == "nmea" else b"") for f in frames)
    assert all(any(got == want for got in delivered) for want in expected)  # an ordered subsequence
    if len(expected) < len(SPANS):
        assert sum(framer.counts.values()) >= 1  # a spoiled frame never goes unnoticed


def _nmea_sentence(kind: str, fields: list[str]) -> Frame:
    body = f"GP{kind}," + ",".join(fields)
    return Frame("nmea", f"${body}*{nmea_checksum(body.encode()):02X}".encode())


FIELD = st.one_of(st.sampled_from(["", "0", "1", "4807.038", "N", "S", "E", "W", "A", "V", "123519.00",
                                   "235959.99", "010124", "999999", "-1", "nan", "inf", "1e9", "M"]),
                  st.text(alphabet="0123456789.-+eE", max_size=10))


# payload sizes the messages really have (ESF-MEAS/ESF-RAW: 1 and 7 entries), so the decoder gets past pyubx2
UBX_SIZES = {"NAV-PVT": (92,), "NAV-PVAT": (116,), "HNR-PVT": (72,), "HNR-INS": (36,), "ESF-INS": (36,),
             "ESF-MEAS": (12, 36), "ESF-RAW": (12, 60)}


def _ubx_frame(class_id: bytes, payload: bytes) -> Frame:
    body = class_id + len(payload).to_bytes(2, "little") + payload
    return Frame("ubx", b"\xb5b" + body + ubx_checksum(body))


UBX_NONSENSE = st.sampled_from(sorted(UBX_WANTED)).flatmap(
    lambda cid: st.one_of(st.sampled_from(UBX_SIZES[UBX_WANTED[cid]]), st.integers(0, 130)).flatmap(
        lambda n: st.binary(min_size=n, max_size=n).map(lambda payload: _ubx_frame(cid, payload))))


@FUZZ
@given(st.lists(st.one_of(
    st.tuples(st.sampled_from(NMEA_WANTED), st.lists(FIELD, max_size=16)).map(lambda t: _nmea_sentence(*t)),
    UBX_NONSENSE), max_size=30))
def test_checksum_valid_nonsense_never_escapes_the_decoder(frames):
    health = HealthCounters("gnss")
    decoder = GnssDecoder(health=health)
    published = []
    for frame in frames:
        published += decoder.decode(frame, 1)
    published += decoder.flush()
    check_published(published)
    rejections = sum(v for k, v in decoder.counts.items() if "error" in k or "bad_field" in k)
    assert health.rejected == rejections
