"""The NMEA+UBX stream framer and the message decoder on their own: chunking, resync, time edge cases."""

from __future__ import annotations

import math
from pathlib import Path

import pynmea2
import pytest
from pyubx2 import GET, UBXMessage, UBXReader

from daemon.spine.health import HealthCounters
from daemon.spine.messages import GnssFix, ImuSample
from drivers.gnss.gnss_messages import WEEK_NS, GnssDecoder, utc_ns
from drivers.gnss.receiver_epochs import covariance_from_ellipse
from drivers.gnss.stream_framer import Frame, StreamFramer, nmea_checksum, ubx_checksum

DATA = Path("/work/shared/data")
GGA_FIELDS = ("4807.038", "N", "01131.000", "E", "1", "08", "0.9", "545.4", "M", "46.9", "M", "", "")
RMC_FIELDS = ("A", "4807.038", "N", "01131.000", "E", "0", "0")


def frames_of(data: bytes, chunk: int) -> tuple[list[Frame], StreamFramer]:
    framer = StreamFramer()
    frames = []
    for i in range(0, len(data), chunk):
        frames += framer.feed(data[i:i + chunk])
    return frames + framer.flush(), framer


def ubx(payload_message: UBXMessage) -> Frame:
    return Frame("ubx", payload_message.serialize())


def nmea(sentence_type: str, *fields: str) -> Frame:
    cls = pynmea2.TalkerSentence.sentence_types[sentence_type]
    return Frame("nmea", cls("GP", sentence_type, fields).render().encode())


def test_checksums_agree_with_the_libraries():
    raw = UBXMessage("NAV", "NAV-PVT", GET, iTOW=1234, lat=1.0, lon=2.0).serialize()
    assert ubx_checksum(raw[2:-2]) == raw[-2:]
    sentence = pynmea2.GGA("GP", "GGA", ("123519", *GGA_FIELDS)).render()
    assert nmea_checksum(sentence[1:-3].encode()) == int(sentence[-2:], 16)


@pytest.mark.skipif(not DATA.is_dir(), reason="shared sensor recordings not present")
@pytest.mark.parametrize("chunk", [1, 7, 4096])
def test_any_chunking_gives_the_same_frames(chunk):
    data = (DATA / "gnss_gpsd/ublox-zed-f9p_hpg1.11.log").read_bytes()[:60_000]
    whole, _ = frames_of(data, len(data))
    pieces, framer = frames_of(data, chunk)
    assert pieces == whole and len(whole) > 200
    assert framer.frame_bytes + framer.skipped_bytes == len(data) and framer.pending_bytes == 0
    assert all(UBXReader.parse(f.data) for f in whole if f.protocol == "ubx")


def test_sync_split_across_reads_and_a_stray_b5_before_it():
    frame = UBXMessage("NAV", "NAV-PVT", GET, iTOW=99).serialize()
    framer = StreamFramer()
    assert framer.feed(b"\xb5\xb5") == []  # the second 0xB5 may start a sync: kept
    assert framer.feed(frame[1:]) == [Frame("ubx", frame)]
    assert framer.counts == {"garbage": 1} and framer.skipped_bytes == 1


def test_a_false_header_delays_but_never_loses_the_frames_behind_it():
    good = [UBXMessage("NAV", "NAV-PVT", GET, iTOW=i).serialize() for i in range(3)]
    false_header = b"\xb5\x62\x01\x07\x00\x10"  # claims 4096 bytes of payload
    framer = StreamFramer()
    assert framer.feed(false_header + b"".join(good)) == []  # still waiting for the claimed length
    assert [f.data for f in framer.flush()] == good
    assert framer.counts == {"ubx_truncated": 1}


def test_over_long_and_binary_interrupted_sentences_are_rejected_one_byte_at_a_time():
    good = nmea("GGA", "123519", *GGA_FIELDS).data + b"\r\n"
    framer = StreamFramer()
    frames = framer.feed(b"$" + b"A" * 1100 + good + b"$GPGGA,1\x00" + good)
    assert [f.data + b"\r\n" for f in frames] == [good, good]
    assert framer.counts == {"nmea_too_long": 1, "nmea_truncated": 1}


def test_rejections_reach_the_health_counters():
    health = HealthCounters("gnss")
    framer = StreamFramer(health)
    framer.feed(b"noise$GPTXT,1*00\r\n")
    framer.flush()
    assert health.rejected == sum(framer.counts.values()) == 2
    assert "nmea_bad_checksum" in health.last_error


def test_gga_before_any_date_is_dropped_and_a_fix_past_midnight_takes_the_next_day():
    health = HealthCounters("gnss")
    decoder = GnssDecoder(health=health)
    assert decoder.decode(nmea("GGA", "235959.50", *GGA_FIELDS), 1) == []
    assert decoder.counts["no_date"] == 1 and health.dropped == 1
    decoder.decode(nmea("RMC", "235959.90", *RMC_FIELDS, "311224", "", ""), 2)
    velocity, fix = decoder.decode(nmea("GGA", "000000.10", *GGA_FIELDS), 3)  # the RMC's, out as an epoch starts
    assert fix.sensor_time_ns == utc_ns(2025, 1, 1, 0, 0, 0) + 100_000_000
    assert velocity.sensor_time_ns == utc_ns(2024, 12, 31, 23, 59, 59) + 900_000_000


def test_empty_position_with_a_fix_flag_is_rejected_not_zero():
    decoder = GnssDecoder()
    decoder.decode(nmea("RMC", "120000", *RMC_FIELDS, "010124", "", ""), 1)
    no_position = ("", "", "", "", *GGA_FIELDS[4:])
    assert decoder.decode(nmea("GGA", "120000", *no_position), 1) == []
    assert decoder.counts["nmea_bad_field_GGA"] == 1


def test_gps_week_rollover_between_pvt_and_ins():
    decoder = GnssDecoder()
    week_end = UBXMessage("NAV", "NAV-PVT", GET, iTOW=604_799_000, year=2024, month=5, day=11, hour=23,
                          min=59, second=41, validDate=1, validTime=1, fixType=3, gnssFixOk=1, lat=1.0,
                          lon=2.0)
    fix, velocity = decoder.decode(ubx(week_end), 1)
    assert velocity.sensor_time_ns == fix.sensor_time_ns and velocity.covariance_type == 0  # no sAcc given
    valid = dict.fromkeys(("xAngRateValid", "yAngRateValid", "zAngRateValid", "xAccelValid", "yAccelValid",
                           "zAccelValid"), 1)
    ins = UBXMessage("HNR", "HNR-INS", GET, iTOW=500, zAccel=9.81, **valid)  # 1.5 s later, in the next week
    [sample] = decoder.decode(ubx(ins), 2)
    assert sample.sensor_time_ns - fix.sensor_time_ns == 1_500_000_000
    assert fix.sensor_time_ns == utc_ns(2024, 5, 11, 23, 59, 41)
    assert WEEK_NS == 604_800 * 10**9


def test_esf_raw_time_tags_unwrap_their_24_bit_counter():
    decoder = GnssDecoder()
    group = {14: 0, 13: 0, 5: 0, 16: 0, 17: 0, 18: 1024}

    def esf_raw(tag: int) -> Frame:
        payload = bytes(4) + b"".join(((k << 24) | v).to_bytes(4, "little") + tag.to_bytes(4, "little")
                                      for k, v in group.items())
        return ubx(UBXMessage("ESF", "ESF-RAW", GET, payload=payload))

    times = [decoder.decode(esf_raw(tag), 0)[0].sensor_time_ns for tag in ((1 << 24) - 256, 0, 256)]
    assert [t - times[0] for t in times] == [0, 10_000_000, 20_000_000]
    decoder.flush()  # port closed: a replugged receiver restarts its clock, that is not a wrap
    assert decoder.decode(esf_raw(256), 0)[0].sensor_time_ns == 10_000_000


def test_esf_ins_is_not_taken_for_a_specific_force():
    decoder = GnssDecoder()
    ins = UBXMessage("ESF", "ESF-INS", GET, iTOW=1000, xAccel=0.5)
    assert decoder.decode(ubx(ins), 0) == []
    assert decoder.counts["ignored_esf_ins_gravity_free"] == 1


def test_the_same_epoch_from_nmea_and_ubx_is_published_once():
    decoder = GnssDecoder()
    pvt = UBXMessage("NAV", "NAV-PVT", GET, iTOW=(6 * 86400 + 18) * 1000 + 250, year=2024, month=5, day=11,
                     hour=0, min=0, second=0, nano=250_000_000, validDate=1, validTime=1, fixType=3,
                     gnssFixOk=1, lat=48.1173, lon=11.5166667, height=592300)
    out = decoder.decode(ubx(pvt), 1)
    decoder.decode(nmea("RMC", "000000.25", *RMC_FIELDS, "110524", "", ""), 1)
    out += decoder.decode(nmea("GGA", "000000.25", *GGA_FIELDS), 1)
    fixes = [m for m in out if isinstance(m, GnssFix)]
    assert len(fixes) == 1 and decoder.counts["duplicate_epoch"] == 1
    assert [type(m).__name__ for m in out] == ["GnssFix", "GnssVelocity"]  # the velocity: NAV-PVT's alone


def test_ellipse_covariance_is_symmetric_positive_with_the_given_axes():
    cov = covariance_from_ellipse(3.0, 1.0, 120.0, 2.0)
    ee, en, ne, nn = cov[0], cov[1], cov[3], cov[4]
    assert en == ne
    trace, det = ee + nn, ee * nn - en * en
    eig = sorted(((trace - math.sqrt(trace**2 - 4 * det)) / 2, (trace + math.sqrt(trace**2 - 4 * det)) / 2))
    assert eig == pytest.approx([1.0, 9.0]) and cov[8] == 4.0


def test_imu_halves_too_far_apart_are_dropped_not_paired():
    decoder = GnssDecoder()

    def esf_meas(tag_ms: int, fields: dict[int, int]) -> Frame:
        payload = tag_ms.to_bytes(4, "little") + (len(fields) << 11).to_bytes(2, "little") + bytes(2)
        payload += b"".join(((k << 24) | v).to_bytes(4, "little") for k, v in fields.items())
        return ubx(UBXMessage("ESF", "ESF-MEAS", GET, payload=payload))

    assert decoder.decode(esf_meas(1000, {16: 0, 17: 0, 18: 1024}), 0) == []
    assert decoder.decode(esf_meas(1100, {14: 0, 13: 0, 5: 0}), 0) == []  # 100 ms later: not one sample
    [sample] = decoder.decode(esf_meas(1105, {16: 0, 17: 0, 18: 2048}), 0)
    assert isinstance(sample, ImuSample) and sample.accel_mps2 == (0.0, 0.0, 2.0)
    assert decoder.counts["imu_unpaired"] == 1
