"""The GNSS driver through a real serial port: a pseudo-terminal whose master side plays the receiver.

Covers decoded values (NMEA rendered by pynmea2, UBX serialised by pyubx2), rejection counting with
garbage interleaved, and unplugging/replugging the port (a symlink that vanishes and comes back).
"""

from __future__ import annotations

import fcntl
import math
import os
import pty
import select
import termios
import threading
import time
import tty
from pathlib import Path

import numpy as np
import pynmea2
import pytest
from pyubx2 import GET, UBXMessage

from daemon.spine.config import GnssConfig
from daemon.spine.health import HealthCounters
from daemon.spine.messages import DriverHealth, GnssFix, ImuSample
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU, health_topic
from drivers.gnss.gnss_messages import utc_ns
from drivers.gnss.receiver_epochs import covariance_from_ellipse
from drivers.gnss.serial_driver import GnssDriverStats, run_gnss_driver

PROBE = pynmea2.TXT("GN", "TXT", ("01", "01", "02", "roadlog probe")).render().encode() + b"\r\n"
LEAP_S = 18  # GPS - UTC in 2024


class PtyReceiver:
    """The receiver's end of a pseudo-terminal, reachable by the driver at a symlink that can vanish."""

    def __init__(self, link: Path):
        self.link = link
        self.plug()

    def plug(self) -> None:
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)  # keep the slave open too: the raw settings and queued bytes stay
        os.symlink(os.ttyname(self.slave), self.link)

    def unplug(self) -> None:
        os.unlink(self.link)
        os.close(self.master)
        os.close(self.slave)

    def write(self, data: bytes, timeout_s: float = 20.0) -> None:
        """Write as fast as the driver reads (the pty buffer is small)."""
        view = memoryview(data)
        deadline = time.monotonic() + timeout_s
        while view:
            assert time.monotonic() < deadline, "the driver stopped reading"
            _, writable, _ = select.select([], [self.master], [], 0.5)
            if writable:
                view = view[os.write(self.master, view[:4096]):]


    def wait_drained(self, timeout_s: float = 20.0) -> None:
        """Until the driver has read every byte written: the slave's input queue stays empty for 0.1 s
        (the kernel moves written bytes into that queue asynchronously)."""
        deadline = time.monotonic() + timeout_s
        empty_since = None
        while empty_since is None or time.monotonic() - empty_since < 0.1:
            assert time.monotonic() < deadline, "the driver stopped reading"
            queued = int.from_bytes(fcntl.ioctl(self.slave, termios.FIONREAD, bytes(4)), "little")
            empty_since = (empty_since or time.monotonic()) if queued == 0 else None
            time.sleep(0.01)


class DriverThread:
    """run_gnss_driver in a thread, publishing into a list."""

    def __init__(self, port: Path, protocol: str = "nmea+ubx"):
        self.published: list[tuple[str, object]] = []
        self.stop = threading.Event()
        self.health = HealthCounters("gnss", expected_rate_hz=1.0)
        self.stats: GnssDriverStats | None = None
        config = GnssConfig(port=str(port), protocol=protocol)

        def target() -> None:
            self.stats = run_gnss_driver(config, str(port), lambda t, m: self.published.append((t, m)),
                                         self.stop, self.health, backoff_s=(0.05, 0.2))

        self.thread = threading.Thread(target=target, daemon=True)
        self.thread.start()

    def of(self, topic: str) -> list:
        return [m for t, m in list(self.published) if t == topic]

    def wait_until(self, condition, timeout_s: float = 20.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.01)

    def wait_open(self, receiver: PtyReceiver) -> None:
        """pyserial flushes the input when it opens the port: probe until a probe sentence gets through."""
        received = self.health.received
        deadline = time.monotonic() + 10.0
        while self.health.received == received:
            assert time.monotonic() < deadline, "the driver never opened the port"
            receiver.write(PROBE)
            time.sleep(0.02)

    def finish(self) -> GnssDriverStats:
        self.stop.set()
        self.thread.join(10.0)
        assert not self.thread.is_alive()
        assert self.stats is not None
        return self.stats


@pytest.fixture
def receiver(tmp_path):
    rx = PtyReceiver(tmp_path / "ttyGNSS")
    yield rx
    if rx.link.is_symlink():
        rx.unplug()


def nmea(sentence_type: str, *fields: str) -> bytes:
    cls = pynmea2.TalkerSentence.sentence_types[sentence_type]
    return cls("GN", sentence_type, fields).render().encode() + b"\r\n"


def rmc(hhmmss: str, status: str = "A", knots: str = "0.0", course: str = "0.0", mode: str = "A") -> bytes:
    return nmea("RMC", hhmmss, status, "5130.0000", "N", "00007.5000", "W", knots, course, "060524", "", "", mode)


def gga(hhmmss: str, lat: str = "5130.1234", lon: str = "00007.5678", quality: str = "1", hdop: str = "0.8",
        altitude: str = "45.6", separation: str = "47.1") -> bytes:
    fields = (hhmmss, lat, "N", lon, "W", quality, "12", hdop, altitude, "M", separation, "M", "", "")
    return nmea("GGA", *fields)


def itow_ms(utc: int) -> int:
    """GPS time of week (ms) of a UTC instant in ns (the GPS week starts Sunday 00:00 GPS time)."""
    gps_epoch = utc_ns(1980, 1, 6, 0, 0, 0)
    return ((utc - gps_epoch) // 1_000_000 + LEAP_S * 1000) % (7 * 86_400_000)


def nav_pvt(utc: int, lat: float, lon: float, height_mm: int, h_acc_mm: int = 1500, v_acc_mm: int = 2500,
            fix_type: int = 3, vel_ned_mm_s: tuple[int, int, int] = (0, 0, 0), s_acc_mm_s: int = 0) -> bytes:
    t = time.gmtime(utc // 1_000_000_000)
    return UBXMessage("NAV", "NAV-PVT", GET, iTOW=itow_ms(utc), year=t.tm_year, month=t.tm_mon, day=t.tm_mday,
                      hour=t.tm_hour, min=t.tm_min, second=t.tm_sec, nano=utc % 1_000_000_000, validDate=1,
                      validTime=1, fullyResolved=1, fixType=fix_type, gnssFixOk=1, numSV=20, lat=lat, lon=lon,
                      height=height_mm, hMSL=height_mm - 47000, hAcc=h_acc_mm, vAcc=v_acc_mm,
                      velN=vel_ned_mm_s[0], velE=vel_ned_mm_s[1], velD=vel_ned_mm_s[2], sAcc=s_acc_mm_s).serialize()


def esf_word(data_type: int, value: int) -> bytes:
    return ((data_type << 24) | (value & 0xFFFFFF)).to_bytes(4, "little")


def esf_meas(time_tag_ms: int, fields: dict[int, int]) -> bytes:
    flags = len(fields) << 11
    payload = time_tag_ms.to_bytes(4, "little") + flags.to_bytes(2, "little") + bytes(2)
    payload += b"".join(esf_word(k, v) for k, v in fields.items())
    return UBXMessage("ESF", "ESF-MEAS", GET, payload=payload).serialize()


def esf_raw(samples: list[tuple[int, dict[int, int]]]) -> bytes:
    payload = bytes(4)
    for tag, fields in samples:
        payload += b"".join(esf_word(k, v) + tag.to_bytes(4, "little") for k, v in fields.items())
    return UBXMessage("ESF", "ESF-RAW", GET, payload=payload).serialize()


def hnr_ins(utc: int, gyro_dps: tuple, accel: tuple) -> bytes:
    valid = dict.fromkeys(("xAngRateValid", "yAngRateValid", "zAngRateValid", "xAccelValid", "yAccelValid",
                           "zAccelValid"), 1)
    return UBXMessage("HNR", "HNR-INS", GET, iTOW=itow_ms(utc), xAngRate=gyro_dps[0], yAngRate=gyro_dps[1],
                      zAngRate=gyro_dps[2], xAccel=accel[0], yAccel=accel[1], zAccel=accel[2],
                      **valid).serialize()


def test_nmea_fixes_take_date_from_rmc_and_covariance_from_gst_or_hdop(receiver):
    driver = DriverThread(receiver.link)
    driver.wait_open(receiver)
    stream = rmc("070809.50")
    # 1: no GST seen yet -> published at once, sigma = HDOP 0.8 x 0.02 m (RTK fixed); its GST comes too late
    stream += gga("070809.50", quality="4")
    stream += nmea("GST", "070809.50", "1.2", "", "", "", "0.45", "0.35", "0.8")
    # 2: GST with an error ellipse for the same epoch
    stream += gga("070809.60", "5130.1240", "00007.5680", hdop="1.1", altitude="45.7")
    stream += nmea("GST", "070809.60", "1.2", "0.5", "0.3", "30.0", "0.45", "0.35", "0.8")
    # 3: GST without the ellipse -> diagonal; 4: no GST -> HDOP, published when epoch 5 starts
    stream += gga("070809.70", "5130.1250", "00007.5690", hdop="1.1", altitude="45.8")
    stream += nmea("GST", "070809.70", "1.2", "", "", "", "0.45", "0.35", "0.8")
    stream += gga("070809.80", "5130.1260", "00007.5700", "2", "1.5", altitude="45.9", separation="")
    stream += rmc("070809.90")
    receiver.write(stream)
    driver.wait_until(lambda: len(driver.of(GNSS_FIX)) == 4)
    stats = driver.finish()
    f1, f2, f3, f4 = driver.of(GNSS_FIX)

    base = utc_ns(2024, 5, 6, 7, 8, 9)
    assert [f.sensor_time_ns - base for f in (f1, f2, f3, f4)] == [500_000_000, 600_000_000, 700_000_000,
                                                                  800_000_000]
    assert f1.latitude_deg == pytest.approx(51 + 30.1234 / 60, abs=1e-12)
    assert f1.longitude_deg == pytest.approx(-(7.5678 / 60), abs=1e-12)
    assert f1.altitude_m == pytest.approx(45.6 + 47.1)  # above the ellipsoid: MSL + geoid separation
    assert f4.altitude_m == pytest.approx(45.9)  # no separation given: MSL
    assert f1.covariance_type == 1
    assert f1.position_covariance == pytest.approx((0.016**2, 0, 0, 0, 0.016**2, 0, 0, 0, 0.032**2))
    assert f2.covariance_type == 3
    assert f2.position_covariance == pytest.approx(covariance_from_ellipse(0.5, 0.3, 30.0, 0.8))
    east_north = [[f2.position_covariance[0], f2.position_covariance[1]],
                  [f2.position_covariance[3], f2.position_covariance[4]]]
    major_axis = (math.sin(math.radians(30)), math.cos(math.radians(30)))
    along_major = sum(major_axis[i] * east_north[i][j] * major_axis[j] for i in range(2) for j in range(2))
    assert along_major == pytest.approx(0.25)
    assert f3.covariance_type == 2
    assert f3.position_covariance == pytest.approx((0.35**2, 0, 0, 0, 0.45**2, 0, 0, 0, 0.8**2))
    assert f4.covariance_type == 1
    assert f4.position_covariance[0] == pytest.approx((1.5 * 0.1) ** 2)  # DGPS: 0.1 m per HDOP
    assert all(f.host_mono_ns > 0 for f in (f1, f2, f3, f4))
    assert stats.framer == {} and driver.health.rejected == 0


def test_ubx_fixes_and_imu_samples_scaled_and_time_tagged(receiver):
    driver = DriverThread(receiver.link)
    driver.wait_open(receiver)
    t0 = utc_ns(2024, 5, 6, 7, 8, 10)
    stream = nav_pvt(t0, 51.5123457, -0.1234568, 45678)
    pvat = UBXMessage("NAV", "NAV-PVAT", GET, iTOW=itow_ms(t0 + 100_000_000), year=2024, month=5, day=6,
                      hour=7, min=8, sec=10, nano=100_000_000, validDate=1, validTime=1, fixType=4,
                      gnssFixOK=1, lat=51.5124, lon=-0.1235, height=45700, hAcc=900, vAcc=700,
                      errEllipseOrient=45.0, errEllipseMajor=2000, errEllipseMinor=1000)
    stream += pvat.serialize()
    stream += hnr_ins(t0 + 150_000_000, (1.5, -2.0, 0.25), (0.25, -0.5, 9.81))
    # ESF-MEAS: accel and gyro in separate messages, 5 ms apart (as the ZED-F9R sample log has them)
    stream += esf_meas(514162, {16: -512, 17: 768, 18: 10035})
    stream += esf_meas(514157, {14: 8192, 13: -4096, 5: 2048})
    # ESF-RAW: two samples 256 ticks (10 ms) apart, gyro temperature included
    group = {12: 2825, 14: 4096, 13: 0, 5: -4096, 16: 1024, 17: -1024, 18: 10240}
    stream += esf_raw([(1000, group), (1256, group)])
    stream += hnr_ins(t0 + 200_000_000, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))  # ESF-RAW outranks it now
    receiver.write(stream)
    driver.wait_until(lambda: len(driver.of(IMU)) == 4 and len(driver.of(GNSS_FIX)) == 2)
    stats = driver.finish()

    pvt_fix, pvat_fix = driver.of(GNSS_FIX)
    assert pvt_fix.sensor_time_ns == t0
    assert (pvt_fix.latitude_deg, pvt_fix.longitude_deg) == pytest.approx((51.5123457, -0.1234568), abs=1e-9)
    assert pvt_fix.altitude_m == pytest.approx(45.678)
    assert pvt_fix.covariance_type == 2
    assert pvt_fix.position_covariance == pytest.approx((2.25, 0, 0, 0, 2.25, 0, 0, 0, 6.25))
    assert pvat_fix.sensor_time_ns == t0 + 100_000_000
    assert pvat_fix.covariance_type == 3
    c = pvat_fix.position_covariance
    assert (c[0], c[4], c[1], c[8]) == pytest.approx((2.5, 2.5, 1.5, 0.49))  # 45 deg ellipse 2 m x 1 m

    ins, meas, raw1, raw2 = driver.of(IMU)
    assert all(isinstance(m, ImuSample) for m in (ins, meas, raw1, raw2))
    assert ins.sensor_time_ns == t0 + 150_000_000
    assert ins.gyro_rps == pytest.approx(tuple(math.radians(v) for v in (1.5, -2.0, 0.25)))
    assert ins.accel_mps2 == pytest.approx((0.25, -0.5, 9.81))
    assert meas.sensor_time_ns == 514162 * 1_000_000
    assert meas.accel_mps2 == pytest.approx((-0.5, 0.75, 10035 / 1024))
    assert meas.gyro_rps == pytest.approx(tuple(math.radians(v) for v in (2.0, -1.0, 0.5)))
    assert (raw1.sensor_time_ns, raw2.sensor_time_ns) == (39_062_500, 49_062_500)
    assert raw1.accel_mps2 == pytest.approx((1.0, -1.0, 10.0))
    assert raw1.gyro_rps == pytest.approx((math.radians(1.0), 0.0, math.radians(-1.0)))
    assert stats.decoder["ignored_lower_imu_source"] == 1
    assert driver.health.rejected == 0 and driver.health.errors == 0


def test_ubx_velocities_in_east_north_up_once_an_epoch_and_a_garbled_one_keeps_its_fix(receiver):
    driver = DriverThread(receiver.link)
    driver.wait_open(receiver)
    t0 = utc_ns(2024, 5, 6, 7, 8, 10)
    second = 1_000_000_000
    stream = rmc("070810.00", knots="10.0", course="90.0")  # a u-blox receiver's RMC comes before its NAV-PVT
    stream += nav_pvt(t0, 51.5, -0.12, 45678, vel_ned_mm_s=(12_345, -6_789, 250), s_acc_mm_s=80)
    stream += gga("070811.00") + nav_pvt(t0 + second, 51.5, -0.12, 45678, vel_ned_mm_s=(1_000, 2_000, -300),
                                         s_acc_mm_s=50)  # the epoch's fix from GGA, its velocity from NAV-PVT
    stream += nav_pvt(t0 + second, 51.5, -0.12, 45678, vel_ned_mm_s=(1_000, 2_000, -300), s_acc_mm_s=50)  # again
    stream += nav_pvt(t0 + 2 * second, 51.5, -0.12, 45678, vel_ned_mm_s=(900_000, 0, 0), s_acc_mm_s=50)  # 900 m/s
    stream += nav_pvt(t0 + 3 * second, 51.5, -0.12, 45678, vel_ned_mm_s=(500, 0, 0))  # no speed accuracy
    stream += rmc("070813.00", knots="10.0", course="90.0")  # NMEA's velocity: not used once UBX gives it
    receiver.write(stream)
    driver.wait_until(lambda: len(driver.of(GNSS_FIX)) == 4 and len(driver.of(GNSS_VELOCITY)) == 3)
    stats = driver.finish()

    assert [f.sensor_time_ns for f in driver.of(GNSS_FIX)] == [t0 + k * second for k in range(4)]
    first, second_epoch, unknown = driver.of(GNSS_VELOCITY)
    assert stats.decoder["ignored_nmea_velocity_ubx_gives_it"] == 2  # the first epoch's RMC, held: its NAV-PVT's
    assert first.sensor_time_ns == t0
    assert first.velocity_enu_mps == pytest.approx((-6.789, 12.345, -0.25))  # north/east/down -> east/north/up
    assert first.covariance_type == 2
    assert first.velocity_covariance == pytest.approx((0.0064, 0, 0, 0, 0.0064, 0, 0, 0, 0.0064))
    assert second_epoch.sensor_time_ns == t0 + second
    assert second_epoch.velocity_enu_mps == pytest.approx((2.0, 1.0, 0.3))
    assert unknown.sensor_time_ns == t0 + 3 * second and unknown.covariance_type == 0
    assert stats.decoder["duplicate_velocity_epoch"] == 1
    assert stats.decoder["ubx_bad_velocity"] == 1 and driver.health.rejected == 1  # counted, its fix kept


def vtg(knots: str, course: str, mode: str = "A") -> bytes:
    kmh = f"{float(knots) * 1.852:.3f}" if knots else ""
    return nmea("VTG", course, "T" if course else "", "", "M", knots, "N", kmh, "K", mode)


def test_nmea_velocities_from_rmc_or_vtg_once_an_epoch_stamped_as_its_fix(receiver):
    """An NMEA receiver (u-blox order: RMC, VTG, GGA): east/north from speed and course over ground, the vertical
    unknown; invalid, empty and garbled ones counted and skipped, their fixes kept; a VTG between two epochs skipped."""
    driver = DriverThread(receiver.link)
    driver.wait_open(receiver)
    stream = rmc("070810.00", knots="10.0", course="90.0") + vtg("10.0", "90.0") + gga("070810.00")  # RMC's
    stream += rmc("070811.00", knots="", course="") + vtg("4.0", "180.0") + gga("070811.00")  # VTG's
    stream += rmc("070812.00", status="V", knots="3.0", course="45.0") + vtg("3.0", "45.0") + gga("070812.00")
    stream += rmc("070813.00", knots="abc", course="45.0") + gga("070813.00")  # garbled, checksum valid
    spoiled = rmc("070814.00", knots="9.0", course="30.0")
    stream += spoiled.replace(b",9.0,", b",8.0,") + gga("070814.00")  # bad checksum: the framer's
    stream += rmc("070815.00", knots="0.03", course="") + gga("070815.00")  # nearly still: no course
    stream += rmc("070816.00", knots="2.0", course="30.0", mode="N") + gga("070816.00")  # mode: not valid
    stream += gga("070817.00") + vtg("5.0", "0.0") + gga("070818.00")  # no RMC: a VTG at an epoch boundary
    stream += rmc("070819.00", knots="1.0", course="0.0")  # ends epoch 070818 (its GGA waits for no GST)
    receiver.write(stream)
    driver.wait_until(lambda: len(driver.of(GNSS_FIX)) == 9 and len(driver.of(GNSS_VELOCITY)) == 4)
    stats = driver.finish()

    fixes = {f.sensor_time_ns: f for f in driver.of(GNSS_FIX)}
    base = utc_ns(2024, 5, 6, 7, 8, 10)
    assert sorted(fixes) == [base + k * 1_000_000_000 for k in range(9)]  # every fix kept
    by_time = {v.sensor_time_ns: v for v in driver.of(GNSS_VELOCITY)}
    assert sorted(by_time) == [base + k * 1_000_000_000 for k in (0, 1, 5, 9)]
    assert all(t in fixes for t in list(by_time)[:3])  # stamped as their epoch's fix
    knot = 1852 / 3600
    east, south, still, last = (by_time[base + k * 1_000_000_000] for k in (0, 1, 5, 9))
    assert east.velocity_enu_mps == pytest.approx((10 * knot, 0.0, 0.0), abs=1e-9)
    assert south.velocity_enu_mps == pytest.approx((0.0, -4 * knot, 0.0), abs=1e-9)
    assert still.velocity_enu_mps == (0.0, 0.0, 0.0)
    assert last.velocity_enu_mps == pytest.approx((0.0, knot, 0.0), abs=1e-9)
    for v in (east, south, last):
        assert v.covariance_type == 1  # approximated: NMEA gives no accuracy
        assert v.velocity_covariance == pytest.approx((0.25**2, 0, 0, 0, 0.25**2, 0, 0, 0, 1000.0**2))
    # a speed of unknown direction: its square shared by the two axes
    assert still.velocity_covariance[0] == pytest.approx(0.25**2 + (0.03 * knot) ** 2 / 2)
    order = [(t, m.sensor_time_ns) for t, m in driver.published if t in (GNSS_FIX, GNSS_VELOCITY)]
    # the first held until the next epoch (a NAV-PVT of its epoch would replace it), then each at once
    assert order.index((GNSS_VELOCITY, base)) > order.index((GNSS_FIX, base))
    assert order.index((GNSS_VELOCITY, base + 5_000_000_000)) < order.index((GNSS_FIX, base + 5_000_000_000))
    assert stats.decoder["duplicate_velocity_epoch"] == 1  # epoch 0's VTG after its RMC
    assert stats.decoder["nmea_velocity_empty"] == 1
    assert stats.decoder["nmea_velocity_invalid"] == 3  # RMC V, its VTG, RMC mode N
    assert stats.decoder["nmea_bad_velocity"] == 1 and driver.health.rejected == 2  # and the bad checksum
    assert stats.decoder["nmea_velocity_without_course"] == 1
    assert stats.decoder["nmea_vtg_epoch_ambiguous"] == 1
    assert stats.framer == {"nmea_bad_checksum": 1}

    from mapping.inputs.drive_inputs import fix_velocities  # what the pose fusion takes
    ordered = [fixes[t] for t in sorted(fixes)]
    velocity, cov = fix_velocities(ordered, driver.of(GNSS_VELOCITY))
    assert [bool(row) for row in np.all(np.isfinite(velocity), axis=1)] == [k in (0, 1, 5) for k in range(9)]
    assert cov[0][2, 2] == 1000.0**2

def test_garbage_bad_checksums_and_truncations_are_counted_and_good_messages_survive(receiver):
    driver = DriverThread(receiver.link)
    driver.wait_open(receiver)
    t0 = utc_ns(2024, 5, 6, 7, 8, 0)
    good_times = []
    stream = rmc("070800.00")
    bad = {"garbage": 0}
    for i in range(12):
        second = 2 * i
        good_nmea = gga(f"0708{second:02d}.00")
        good_ubx = nav_pvt(t0 + (second + 1) * 10**9, 51.5, -0.1, 45000)
        good_times += [t0 + second * 10**9, t0 + (second + 1) * 10**9]
        spoiled_nmea = gga("070859.00")
        spoiled_ubx = bytearray(nav_pvt(t0 + 59 * 10**9, 51.5, -0.1, 45000))
        spoiled_ubx[20] ^= 0x01
        junk = [
            ("nmea_bad_checksum", spoiled_nmea.replace(b"5130.1234", b"5130.1235")),
            ("nmea_no_checksum", spoiled_nmea[: spoiled_nmea.index(b"*")] + b"\r\n"),
            ("nmea_truncated", spoiled_nmea[:30]),  # cut: the next sentence's '$' follows
            ("ubx_bad_checksum", bytes(spoiled_ubx)),
            ("ubx_bad_checksum", bytes(spoiled_ubx[:40])),  # cut UBX frame: its length runs over what follows
            ("ubx_too_long", b"\xb5\x62\x01\x07\xff\xff"),  # a false header
            ("nmea_truncated", b"$"),  # a stray sync before a UBX frame
            ("garbage", b"\x00\x17noise\xff\xb5\x00"),
        ][i % 8]
        bad[junk[0]] = bad.get(junk[0], 0) + 1
        stream += junk[1] + good_nmea + good_ubx if i % 2 else good_nmea + junk[1] + good_ubx
    receiver.write(stream)
    driver.wait_until(lambda: len(driver.of(GNSS_FIX)) == len(good_times))
    stats = driver.finish()
    fixes = driver.of(GNSS_FIX)
    assert sorted(f.sensor_time_ns for f in fixes) == sorted(good_times)
    assert all(f.latitude_deg == pytest.approx(51.5, abs=0.01) for f in fixes)
    bad_garbage = bad.pop("garbage")
    for kind, n in bad.items():
        assert stats.framer.get(kind, 0) == n, kind
    # a cut UBX frame may also leave its tail as garbage between frames: at least the injected runs
    assert stats.framer["garbage"] >= bad_garbage
    assert driver.health.rejected == sum(stats.framer.values())
    probes = stats.decoder["ignored"]
    assert driver.health.received == probes + 1 + len(good_times)  # every valid frame, nothing more


def test_unplug_and_replug_reopens_with_backoff_and_continues(receiver):
    driver = DriverThread(receiver.link)
    driver.wait_open(receiver)
    receiver.write(rmc("070800.00") + b"".join(gga(f"0708{s:02d}.00") for s in range(1, 6))
                   + gga("070806.00")[:25])  # unplugged mid-sentence
    driver.wait_until(lambda: len(driver.of(GNSS_FIX)) == 5)
    receiver.unplug()
    driver.wait_until(lambda: driver.health.errors >= 3)  # the read failure, then failed reopenings
    driver.wait_until(lambda: any(h.state == "error" and "closed" in h.detail
                                  for h in driver.of(health_topic("gnss"))), timeout_s=5.0)
    errors_while_away = driver.health.errors
    time.sleep(0.5)
    # backoff doubles 0.05 -> 0.2 s: about 3 attempts in 0.5 s, never a busy loop
    assert 1 <= driver.health.errors - errors_while_away <= 6
    receiver.plug()
    driver.wait_open(receiver)
    receiver.write(rmc("070806.50") + b"".join(gga(f"0708{s:02d}.00") for s in range(7, 12)))
    driver.wait_until(lambda: len(driver.of(GNSS_FIX)) == 10)
    n_health = len(driver.of(health_topic("gnss")))
    driver.wait_until(lambda: len(driver.of(health_topic("gnss"))) > n_health, timeout_s=3.0)
    back = driver.of(health_topic("gnss"))[-1]
    assert back.state != "error" and " open;" in back.detail
    stats = driver.finish()
    seconds = [round((f.sensor_time_ns - utc_ns(2024, 5, 6, 7, 8, 0)) / 1e9) for f in driver.of(GNSS_FIX)]
    assert seconds == [1, 2, 3, 4, 5, 7, 8, 9, 10, 11]
    assert stats.framer == {"nmea_truncated": 1}  # the sentence the unplugging cut
    assert "read" in driver.health.last_error or "open" in driver.health.last_error
    healths = driver.of(health_topic("gnss"))
    assert all(isinstance(h, DriverHealth) for h in healths)
    assert healths[-1].state != "error" and " stopped;" in healths[-1].detail


def test_health_is_published_about_once_a_second_while_the_port_is_missing(tmp_path):
    driver = DriverThread(tmp_path / "no_such_port")
    time.sleep(2.3)
    stats = driver.finish()
    healths = driver.of(health_topic("gnss"))
    assert 3 <= len(healths) <= 5
    assert all(h.state == "error" and " closed;" in h.detail for h in healths[:-1])
    assert " stopped;" in healths[-1].detail  # the last word at shutdown
    assert driver.health.errors >= 5 and "open" in driver.health.last_error
    assert stats.framer == {} and driver.of(GNSS_FIX) == []


def test_protocol_setting_ignores_the_other_protocol(receiver):
    driver = DriverThread(receiver.link, protocol="ubx")
    driver.wait_open(receiver)
    t0 = utc_ns(2024, 5, 6, 7, 8, 10)
    receiver.write(rmc("070800.00") + nav_pvt(t0, 51.5, -0.1, 45000))
    driver.wait_until(lambda: len(driver.of(GNSS_FIX)) == 1)
    stats = driver.finish()
    assert isinstance(driver.of(GNSS_FIX)[0], GnssFix)
    assert stats.decoder["ignored_nmea"] >= 2  # the probe(s) and the RMC
