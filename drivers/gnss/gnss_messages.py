"""Turns checked NMEA and UBX frames into GnssFix, GnssVelocity and ImuSample messages (times, units, covariances).

Fixes come from NMEA GGA (date from RMC or ZDA, covariance from GST of the same epoch, else approximated
from HDOP) and from UBX NAV-PVT, NAV-PVAT and HNR-PVT (covariance from the error ellipse or hAcc/vAcc).
`altitude_m` is above the WGS84 ellipsoid (GGA: MSL altitude + geoid separation; MSL when the sentence
leaves the separation empty). A receiver epoch is published once, by the first message that gives it.
Fix `sensor_time_ns` is UTC in ns since 1970: NMEA time of day + date; UBX GPS time of week (iTOW) mapped
to UTC through the UTC date/time the receiver sends in the same NAV-PVT/PVAT/HNR-PVT message.
Velocities come from UBX NAV-PVT and NAV-PVAT and, for a receiver that sends no UBX velocity, from NMEA RMC or VTG,
once an epoch, stamped as the epoch's fix: epoch_velocity.py says which and how.
HNR-PVT (no velocity vector) gives none.

IMU samples come from ESF-RAW, ESF-MEAS (the IMU's own axes, specific force in m/s^2, rate in rad/s;
`sensor_time_ns` is the receiver's sensor time tag, a clock since its start, not UTC) or HNR-INS
(u-blox vehicle axes, with gravity; UTC). Only the best source the receiver sends is used (ESF-RAW >
ESF-MEAS > HNR-INS). ESF-INS is not used: its accelerations are gravity-free, not a specific force.
"""

from __future__ import annotations

import datetime as dt
import math
from collections import Counter, deque
from dataclasses import dataclass, replace

import pynmea2
from pyubx2 import UBXReader

from daemon.spine.health import HealthCounters
from daemon.spine.messages import GnssFix, GnssVelocity, ImuSample, Vec3
from drivers.gnss.epoch_velocity import NMEA_NOT_VALID_MODES, EpochVelocity
from drivers.gnss.receiver_epochs import (
    NS_PER_MS,
    NS_PER_S,
    RECENT_EPOCHS,
    UNKNOWN_COVARIANCE,
    Covariance,
    covariance_diagonal,
    covariance_from_ellipse,
    epoch_key,
)
from drivers.gnss.stream_framer import Frame

DAY_NS = 86_400 * NS_PER_S
WEEK_NS = 7 * DAY_NS
_UNIX_EPOCH_ORDINAL = dt.date(1970, 1, 1).toordinal()

# ESF data types (u-blox interface description, "ESF measurement data"): scale 2^-12 deg/s, 2^-10 m/s^2.
GYRO_AXIS_BY_TYPE = {14: 0, 13: 1, 5: 2}
ACCEL_AXIS_BY_TYPE = {16: 0, 17: 1, 18: 2}
GYRO_LSB_RPS = math.radians(2.0**-12)
ACCEL_LSB_MPS2 = 2.0**-10
# The ESF-RAW sensor time tag counts 39.0625 us ticks (25.6 kHz) in a 24-bit counter. The UBX spec gives
# no unit; this is the IMU's sensor-time tick, as used by Swift Navigation's gnss-converters (ubx_sbp.c).
ESF_RAW_TICK_NS_TIMES_2 = 78_125  # 39062.5 ns
ESF_RAW_TICK_BITS = 24
IMU_PAIR_WINDOW_NS = 20 * NS_PER_MS  # accel and gyro triples this close in time form one sample
IMU_SOURCE_RANK = {"ESF-RAW": 3, "ESF-MEAS": 2, "HNR-INS": 1}
# GGA without GST: sigma = HDOP x a per-fix-quality error, as ROS nmea_navsat_driver does (metres).
HDOP_ERROR_BY_QUALITY = {1: 4.0, 2: 0.1, 3: 4.0, 4: 0.02, 5: 4.0, 6: 4.0, 9: 3.0}
UBX_FIX_TYPES = (1, 2, 3, 4)  # dead reckoning, 2D, 3D, GNSS + dead reckoning
UBX_WANTED = {
    b"\x01\x07": "NAV-PVT",
    b"\x01\x17": "NAV-PVAT",
    b"\x28\x00": "HNR-PVT",
    b"\x28\x02": "HNR-INS",
    b"\x10\x02": "ESF-MEAS",
    b"\x10\x03": "ESF-RAW",
    b"\x10\x15": "ESF-INS",
}
NMEA_WANTED = ("GGA", "RMC", "GST", "ZDA", "VTG")
# Field values that are wrong in a checksum-valid message: counted as rejected, never raised.
_BAD_FIELD_ERRORS = (ValueError, TypeError, ArithmeticError, AttributeError, IndexError, KeyError)


def utc_ns(year: int, month: int, day: int, hour: int, minute: int, second: int, nano: int = 0) -> int:
    """UTC calendar time to ns since 1970 (second 60, a leap second, runs into the next minute)."""
    days = dt.date(year, month, day).toordinal() - _UNIX_EPOCH_ORDINAL
    if not (0 <= hour < 24 and 0 <= minute < 60 and 0 <= second <= 60):
        raise ValueError(f"bad time of day {hour}:{minute}:{second}")
    return (days * 86_400 + hour * 3600 + minute * 60 + second) * NS_PER_S + nano


def _checked(*values: float) -> None:
    """Finite and not negative (altitudes excepted by the caller), or the field is bad."""
    for v in values:
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"bad value {v}")


def _time_of_day_ns(t: dt.time | None) -> int:
    if t is None:
        raise ValueError("no time of day")
    return ((t.hour * 60 + t.minute) * 60 + t.second) * NS_PER_S + t.microsecond * 1000


def _nmea_degrees(sentence: pynmea2.TalkerSentence) -> tuple[float, float]:
    # pynmea2 turns an empty latitude into 0.0: check the raw fields first
    hemispheres = sentence.lat_dir in ("N", "S") and sentence.lon_dir in ("E", "W")
    if not (sentence.lat and sentence.lon and hemispheres):
        raise ValueError("empty or malformed latitude/longitude")
    lat, lon = float(sentence.latitude), float(sentence.longitude)
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0):
        raise ValueError(f"latitude/longitude out of range: {lat}, {lon}")
    return lat, lon


@dataclass(slots=True)
class _PendingFix:
    """A GGA fix waiting for the GST of its epoch."""

    fix: GnssFix
    time_of_day_ns: int
    hdop_covariance: Covariance
    hdop_covariance_type: int


class GnssDecoder:
    """Stateful: keeps the date, the GPS-week to UTC mapping, a GGA waiting for its GST, half IMU samples, and its
    epochs' velocities in an EpochVelocity."""

    def __init__(self, protocol: str = "nmea+ubx", health: HealthCounters | None = None) -> None:
        self.counts: Counter[str] = Counter()
        self._protocols = set(protocol.split("+"))
        self._health = health
        self._date_midnight_ns: int | None = None  # UTC midnight of the last RMC/ZDA date ...
        self._date_time_of_day_ns = 0  # ... and that sentence's time of day
        self._pending: _PendingFix | None = None
        self._early_gst: tuple[int, Covariance, int] | None = None  # a GST that came before its GGA
        self._gst_seen = False
        self._week_start_utc_ns: int | None = None  # UTC time of GPS time-of-week 0, from the receiver
        self._week_anchor_itow_ms = 0
        self._recent_fix_ms: deque[int] = deque(maxlen=RECENT_EPOCHS)
        self._velocities = EpochVelocity(self.counts, self._reject, self._drop, self._nmea_utc_ns)
        self._imu_source_rank = 0
        self._imu_pending: dict[str, tuple[int, Vec3]] = {}
        self._esf_raw_last_tick: int | None = None
        self._esf_raw_wraps = 0

    # ---- entry points -------------------------------------------------------------------------------
    def decode(self, frame: Frame, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        if frame.protocol not in self._protocols:
            self.counts[f"ignored_{frame.protocol}"] += 1
            return []
        if frame.protocol == "nmea":
            return self._decode_nmea(frame.data.decode("ascii"), host_mono_ns)
        return self._decode_ubx(frame.data, host_mono_ns)

    def flush(self) -> list[GnssFix | GnssVelocity | ImuSample]:
        """The stream has ended (port closed): publish the GGA still waiting for its GST, drop half IMU
        samples and forget the IMU clock, which restarts if the receiver does."""
        out = self._flush_pending(None) + self._velocities.flush()
        for _ in self._imu_pending:
            self._drop("imu_unpaired")
        self._imu_pending.clear()
        self._esf_raw_last_tick = None
        self._esf_raw_wraps = 0
        return out

    # ---- bookkeeping --------------------------------------------------------------------------------
    def _reject(self, kind: str, exc: BaseException | None = None) -> None:
        self.counts[kind] += 1
        if self._health is not None:
            self._health.count_rejected(f"{kind}: {exc}" if exc is not None else kind)

    def _drop(self, kind: str) -> None:
        self.counts[kind] += 1
        if self._health is not None:
            self._health.dropped += 1

    def _emit_fix(self, fix: GnssFix) -> list[GnssFix | GnssVelocity | ImuSample]:
        epoch_ms = epoch_key(fix.sensor_time_ns)
        if epoch_ms in self._recent_fix_ms:
            self.counts["duplicate_epoch"] += 1
            return []
        self._recent_fix_ms.append(epoch_ms)
        self.counts["fix"] += 1
        return [fix]

    # ---- NMEA ---------------------------------------------------------------------------------------
    def _decode_nmea(self, text: str, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        kind = text[3:6] if not text.startswith("$P") else ""
        if kind not in NMEA_WANTED:
            self.counts["ignored"] += 1
            return []
        try:
            sentence = pynmea2.parse(text, check=True)
        except Exception as exc:  # pynmea2 raises many kinds on malformed input; each one is a rejection
            self._reject(f"nmea_parse_error_{kind}", exc)
            return []
        try:
            if kind == "VTG":
                self._velocities.on_vtg(sentence, host_mono_ns)
                return []
            time_of_day = _time_of_day_ns(sentence.timestamp)
            no_fix = (kind == "RMC" and (sentence.status != "A" or sentence.mode_indicator in NMEA_NOT_VALID_MODES)
                      or kind == "GGA" and not int(sentence.gps_qual or 0))
        except _BAD_FIELD_ERRORS as exc:
            self._reject(f"nmea_bad_field_{kind}", exc)
            return []
        out: list[GnssFix | GnssVelocity | ImuSample] = []
        out += self._velocities.on_timed_sentence(time_of_day, no_fix)
        try:
            if kind == "GGA":
                return out + self._on_gga(sentence, host_mono_ns)
            if kind == "GST":
                return out + self._on_gst(sentence)
            out += self._on_date(sentence, kind)
        except _BAD_FIELD_ERRORS as exc:
            self._reject(f"nmea_bad_field_{kind}", exc)
            return out
        if kind == "RMC":
            return out + self._velocities.on_rmc(sentence, time_of_day, no_fix, host_mono_ns)
        return out

    def _on_date(self, sentence: pynmea2.TalkerSentence, kind: str) -> list[GnssFix | GnssVelocity | ImuSample]:
        time_of_day = _time_of_day_ns(sentence.timestamp)
        out = self._flush_pending(time_of_day)
        if kind == "RMC":
            date = sentence.datestamp
            if date is None:
                raise ValueError("RMC without a date")
        else:
            date = dt.date(int(sentence.year), int(sentence.month), int(sentence.day))
        self._date_midnight_ns = (date.toordinal() - _UNIX_EPOCH_ORDINAL) * DAY_NS
        self._date_time_of_day_ns = time_of_day
        return out

    def _nmea_utc_ns(self, time_of_day_ns: int) -> int | None:
        if self._date_midnight_ns is None:
            return None
        midnight = self._date_midnight_ns
        if time_of_day_ns - self._date_time_of_day_ns < -DAY_NS // 2:
            midnight += DAY_NS  # past midnight since the last date
        elif time_of_day_ns - self._date_time_of_day_ns > DAY_NS // 2:
            midnight -= DAY_NS  # a fix from before midnight, the date came after it
        return midnight + time_of_day_ns

    def _on_gga(self, gga: pynmea2.TalkerSentence, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        time_of_day = _time_of_day_ns(gga.timestamp)
        out = self._flush_pending(time_of_day)
        quality = int(gga.gps_qual or 0)
        if quality == 0:
            self.counts["no_fix"] += 1
            return out
        lat, lon = _nmea_degrees(gga)
        if gga.altitude is None:
            raise ValueError("GGA fix without altitude")
        altitude = float(gga.altitude) + (float(gga.geo_sep) if gga.geo_sep else 0.0)
        _checked(abs(altitude))
        sensor_time = self._nmea_utc_ns(time_of_day)
        if sensor_time is None:
            self._drop("no_date")
            return out
        hdop = float(gga.horizontal_dil) if gga.horizontal_dil else math.nan
        if not math.isnan(hdop):
            _checked(hdop)
        sigma = hdop * HDOP_ERROR_BY_QUALITY.get(quality, 4.0)
        if math.isfinite(sigma):
            hdop_cov, hdop_type = covariance_diagonal(sigma, sigma, 2.0 * sigma), 1
        else:
            hdop_cov, hdop_type = UNKNOWN_COVARIANCE, 0
        fix = GnssFix(sensor_time_ns=sensor_time, host_mono_ns=host_mono_ns, latitude_deg=lat,
                      longitude_deg=lon, altitude_m=altitude)
        if self._early_gst is not None and self._early_gst[0] == time_of_day:
            _, cov, cov_type = self._early_gst
            self._early_gst = None
            return out + self._emit_fix(replace(fix, position_covariance=cov, covariance_type=cov_type))
        if self._gst_seen:
            self._pending = _PendingFix(fix, time_of_day, hdop_cov, hdop_type)
            return out
        return out + self._emit_fix(replace(fix, position_covariance=hdop_cov, covariance_type=hdop_type))

    def _on_gst(self, gst: pynmea2.TalkerSentence) -> list[GnssFix | GnssVelocity | ImuSample]:
        time_of_day = _time_of_day_ns(gst.timestamp)
        out = self._flush_pending(time_of_day)
        sig_lat, sig_lon, sig_alt = gst.std_dev_latitude, gst.std_dev_longitude, gst.std_dev_altitude
        if sig_lat is None or sig_lon is None or sig_alt is None:
            raise ValueError("GST without latitude/longitude/altitude sigmas")
        _checked(float(sig_lat), float(sig_lon), float(sig_alt))
        major, minor, orientation = gst.std_dev_major, gst.std_dev_minor, gst.orientation
        if major is not None and minor is not None and orientation is not None:
            _checked(float(major), float(minor), abs(float(orientation)))
            cov = covariance_from_ellipse(float(major), float(minor), float(orientation), float(sig_alt))
            cov_type = 3
        else:
            cov, cov_type = covariance_diagonal(float(sig_lon), float(sig_lat), float(sig_alt)), 2
        self._gst_seen = True
        if self._pending is not None and self._pending.time_of_day_ns == time_of_day:
            fix = replace(self._pending.fix, position_covariance=cov, covariance_type=cov_type)
            self._pending = None
            return out + self._emit_fix(fix)
        self._early_gst = (time_of_day, cov, cov_type)
        return out

    def _flush_pending(self, time_of_day_ns: int | None) -> list[GnssFix | GnssVelocity | ImuSample]:
        """Publish the waiting GGA fix with its HDOP covariance once a sentence of another epoch arrives."""
        pending = self._pending
        if pending is None or pending.time_of_day_ns == time_of_day_ns:
            return []
        self._pending = None
        self.counts["fix_without_gst"] += 1
        fix = replace(pending.fix, position_covariance=pending.hdop_covariance,
                      covariance_type=pending.hdop_covariance_type)
        return self._emit_fix(fix)

    # ---- UBX ----------------------------------------------------------------------------------------
    def _decode_ubx(self, data: bytes, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        name = UBX_WANTED.get(data[2:4])
        if name is None:
            self.counts["ignored"] += 1
            return []
        if name == "ESF-INS":
            self.counts["ignored_esf_ins_gravity_free"] += 1
            return []
        try:
            msg = UBXReader.parse(data)
        except Exception as exc:  # pyubx2 raises several kinds on malformed payloads; each one is a rejection
            self._reject(f"ubx_parse_error_{name}", exc)
            return []
        try:
            if name in ("NAV-PVT", "NAV-PVAT", "HNR-PVT"):
                return self._on_pvt(name, msg, host_mono_ns)
            return self._on_imu(name, msg, host_mono_ns)
        except _BAD_FIELD_ERRORS as exc:
            self._reject(f"ubx_bad_field_{name}", exc)
            return []

    def _itow_utc_ns(self, itow_ms: int) -> int | None:
        if self._week_start_utc_ns is None:
            return None
        t = self._week_start_utc_ns + itow_ms * NS_PER_MS
        if itow_ms - self._week_anchor_itow_ms < -WEEK_NS // NS_PER_MS // 2:
            t += WEEK_NS  # the week rolled over since the anchor
        elif itow_ms - self._week_anchor_itow_ms > WEEK_NS // NS_PER_MS // 2:
            t -= WEEK_NS
        return t

    def _on_pvt(self, name: str, msg, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        if msg.validDate and msg.validTime:
            second = msg.sec if name == "NAV-PVAT" else msg.second
            utc = utc_ns(msg.year, msg.month, msg.day, msg.hour, msg.min, second, msg.nano)
            # iTOW is GPS time; the UTC of the same epoch fixes the week start (a whole second) in UTC
            self._week_start_utc_ns = round((utc - msg.iTOW * NS_PER_MS) / NS_PER_S) * NS_PER_S
            self._week_anchor_itow_ms = msg.iTOW
        if name == "HNR-PVT":
            fix_ok, fix_type = msg.GPSfixOK, msg.gpsFix
        else:
            fix_ok, fix_type = (msg.gnssFixOK if name == "NAV-PVAT" else msg.gnssFixOk), msg.fixType
        if not (fix_ok and fix_type in UBX_FIX_TYPES):
            self.counts["no_fix"] += 1
            return []
        sensor_time = self._itow_utc_ns(msg.iTOW)
        if sensor_time is None:
            self._drop("no_time")
            return []
        lat, lon = float(msg.lat), float(msg.lon)
        if not (abs(lat) <= 90.0 and abs(lon) <= 180.0):
            raise ValueError(f"latitude/longitude out of range: {lat}, {lon}")
        h_acc, v_acc = msg.hAcc / 1000.0, msg.vAcc / 1000.0
        if name == "NAV-PVAT":
            cov = covariance_from_ellipse(msg.errEllipseMajor / 1000.0, msg.errEllipseMinor / 1000.0,
                                          float(msg.errEllipseOrient), v_acc)
            cov_type = 3
        else:
            cov, cov_type = covariance_diagonal(h_acc, h_acc, v_acc), 2
        fix = GnssFix(sensor_time_ns=sensor_time, host_mono_ns=host_mono_ns, latitude_deg=lat,
                      longitude_deg=lon, altitude_m=msg.height / 1000.0, position_covariance=cov,
                      covariance_type=cov_type)
        velocity = self._velocities.on_ubx(msg, sensor_time, host_mono_ns) if name != "HNR-PVT" else []
        return self._emit_fix(fix) + velocity

    # ---- IMU ----------------------------------------------------------------------------------------
    def _on_imu(self, name: str, msg, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        rank = IMU_SOURCE_RANK[name]
        if rank < self._imu_source_rank:
            self.counts["ignored_lower_imu_source"] += 1
            return []
        if rank > self._imu_source_rank:
            self._imu_source_rank = rank
            self._imu_pending.clear()
        if name == "HNR-INS":
            return self._on_hnr_ins(msg, host_mono_ns)
        triples = self._esf_raw_triples(msg) if name == "ESF-RAW" else self._esf_meas_triples(msg)
        out: list[GnssFix | GnssVelocity | ImuSample] = []
        for kind, t, xyz in triples:
            out += self._pair_imu(kind, t, xyz, host_mono_ns)
        return out

    def _on_hnr_ins(self, msg, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        valid = (msg.xAngRateValid, msg.yAngRateValid, msg.zAngRateValid,
                 msg.xAccelValid, msg.yAccelValid, msg.zAccelValid)
        if not all(valid):
            self._drop("imu_invalid")
            return []
        sensor_time = self._itow_utc_ns(msg.iTOW)
        if sensor_time is None:
            self._drop("no_time")
            return []
        gyro = tuple(math.radians(float(v)) for v in (msg.xAngRate, msg.yAngRate, msg.zAngRate))
        accel = (float(msg.xAccel), float(msg.yAccel), float(msg.zAccel))
        self.counts["imu"] += 1
        return [ImuSample(sensor_time_ns=sensor_time, host_mono_ns=host_mono_ns, accel_mps2=accel,
                          gyro_rps=gyro)]

    def _esf_raw_ticks(self, tag: int) -> int:
        """Unwraps the 24-bit ESF-RAW sensor time tag into a count since the first sample."""
        tag &= (1 << ESF_RAW_TICK_BITS) - 1
        half_range = 1 << (ESF_RAW_TICK_BITS - 1)
        if self._esf_raw_last_tick is not None and tag < self._esf_raw_last_tick - half_range:
            self._esf_raw_wraps += 1
        self._esf_raw_last_tick = tag
        return (self._esf_raw_wraps << ESF_RAW_TICK_BITS) + tag

    def _esf_raw_triples(self, msg) -> list[tuple[str, int, Vec3]]:
        by_tag: dict[int, dict[int, int]] = {}
        i = 1
        while hasattr(msg, f"data_{i:02d}"):
            word = int.from_bytes(getattr(msg, f"data_{i:02d}"), "little")
            tag = int.from_bytes(getattr(msg, f"sTag_{i:02d}"), "little")
            by_tag.setdefault(tag, {})[word >> 24] = word & 0xFFFFFF
            i += 1
        triples = []
        for tag, values in by_tag.items():
            t = self._esf_raw_ticks(tag) * ESF_RAW_TICK_NS_TIMES_2 // 2
            triples += self._axes_to_triples(values, t)
        return triples

    def _esf_meas_triples(self, msg) -> list[tuple[str, int, Vec3]]:
        values = {}
        for i in range(1, msg.numMeas + 1):
            values[getattr(msg, f"dataType_{i:02d}")] = getattr(msg, f"dataField_{i:02d}")
        return self._axes_to_triples(values, msg.timeTag * NS_PER_MS)

    def _axes_to_triples(self, values: dict[int, int], t: int) -> list[tuple[str, int, Vec3]]:
        """(kind, time, xyz) for each complete gyro or accel triple among ESF data fields of one time tag."""
        triples = []
        sensors = (("gyro", GYRO_AXIS_BY_TYPE, GYRO_LSB_RPS), ("accel", ACCEL_AXIS_BY_TYPE, ACCEL_LSB_MPS2))
        for kind, axes, lsb in sensors:
            present = [dtype for dtype in axes if dtype in values]
            if not present:
                continue
            if len(present) < 3:
                self._drop("imu_incomplete")
                continue
            xyz = [0.0, 0.0, 0.0]
            for dtype, axis in axes.items():
                raw = values[dtype]
                xyz[axis] = (raw - (1 << 24) if raw & 0x800000 else raw) * lsb
            triples.append((kind, t, (xyz[0], xyz[1], xyz[2])))
        return triples

    def _pair_imu(self, kind: str, t: int, xyz: Vec3, host_mono_ns: int) -> list[GnssFix | GnssVelocity | ImuSample]:
        other = "accel" if kind == "gyro" else "gyro"
        if kind in self._imu_pending:
            self._drop("imu_unpaired")
        self._imu_pending[kind] = (t, xyz)
        if other not in self._imu_pending:
            return []
        t_other, xyz_other = self._imu_pending.pop(other)
        if abs(t - t_other) > IMU_PAIR_WINDOW_NS:
            self._drop("imu_unpaired")
            return []
        del self._imu_pending[kind]
        accel, gyro = (xyz, xyz_other) if kind == "accel" else (xyz_other, xyz)
        self.counts["imu"] += 1
        return [ImuSample(sensor_time_ns=max(t, t_other), host_mono_ns=host_mono_ns, accel_mps2=accel,
                          gyro_rps=gyro)]
