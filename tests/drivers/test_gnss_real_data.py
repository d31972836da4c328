"""Real receiver recordings fed through a pseudo-terminal into the GNSS driver, as fast as it reads.

- u-blox ZED-F9R drive (NAV-PVAT + NAV-ATT + ESF-STATUS): its 527 s trajectory comes out whole.
- RTKLIB's raw-measurement stream (RXM-RAW/SFRB + NMEA, cut mid-frame at the end): no parse error.
- gpsd's regression captures: our fixes agree with gpsd's own decoding in the .chk files.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from pathlib import Path

import pytest

from daemon.spine.messages import GnssFix
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU
from drivers.gnss.gnss_messages import utc_ns
from tests.drivers.test_gnss_driver import DriverThread, PtyReceiver

DATA = Path("/work/shared/data")
EARTH_RADIUS_M = 6_378_137.0
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared sensor recordings not present")


def feed(path: Path, tmp_path: Path) -> tuple[DriverThread, list[GnssFix]]:
    receiver = PtyReceiver(tmp_path / "ttyGNSS")
    driver = DriverThread(receiver.link)
    try:
        driver.wait_open(receiver)
        receiver.write(path.read_bytes())
        receiver.wait_drained()
        driver.finish()
    finally:
        receiver.unplug()
    return driver, driver.of(GNSS_FIX)


def parse_errors(decoder_counts: dict[str, int]) -> dict[str, int]:
    return {k: v for k, v in decoder_counts.items() if "error" in k or "bad_field" in k}


def test_zed_f9r_drive_yields_its_527_s_trajectory(tmp_path):
    driver, fixes = feed(DATA / "gnss_pyubx2/pygpsdata-SF-calibration.log", tmp_path)
    assert driver.stats.framer == {}
    assert parse_errors(driver.stats.decoder) == {}
    assert len(fixes) == 527
    times = [f.sensor_time_ns for f in fixes]
    assert times == sorted(times)
    assert times[0] == utc_ns(2026, 4, 20, 13, 48, 55)
    assert (times[-1] - times[0]) / 1e9 == pytest.approx(526.0)
    lat0, lon0 = fixes[0].latitude_deg, fixes[0].longitude_deg
    metres_per_deg_east = math.radians(1.0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    east = [(f.longitude_deg - lon0) * metres_per_deg_east for f in fixes]
    north = [math.radians(f.latitude_deg - lat0) * EARTH_RADIUS_M for f in fixes]
    steps = [math.hypot(east[i + 1] - east[i], north[i + 1] - north[i]) for i in range(len(fixes) - 1)]
    assert max(steps) < 16.0  # the log's top speed is about 15 m/s, fixes come at 1 Hz
    assert 2500 < sum(steps) < 3200  # a 2.8 km drive
    assert max(math.hypot(e, n) for e, n in zip(east, north, strict=True)) < 1500
    assert all(51.24 < f.latitude_deg < 51.27 and -0.58 < f.longitude_deg < -0.56 for f in fixes)
    assert all(60 < f.altitude_m < 110 for f in fixes)
    assert all(f.covariance_type == 3 and 0 < f.position_covariance[0] < 25 for f in fixes)
    assert driver.health.received == 1621 + driver.stats.decoder["ignored"] - 1094  # frames + probes
    assert driver.health.rejected == 0 and driver.health.errors == 0


def test_rtklib_raw_measurement_stream_goes_through_without_errors(tmp_path):
    driver, fixes = feed(DATA / "gnss_rtklib/ubx_20080526.ubx", tmp_path)
    assert parse_errors(driver.stats.decoder) == {}
    assert driver.stats.framer == {"ubx_truncated": 1}  # the capture stops inside its last frame
    assert len(fixes) == 242  # one GGA per epoch, dated by RMC
    assert driver.stats.skipped_bytes == 18
    assert driver.health.errors == 0
    assert driver.of(IMU) == []


def first_tpv_with_altitude_by_time_of_day(chk: Path) -> dict[str, dict]:
    """gpsd's first TPV report per time of day that has an altitude (the one its GGA produced)."""
    reports: dict[str, dict] = {}
    for line in chk.read_text().splitlines():
        if line.startswith('{"class":"TPV"'):
            tpv = json.loads(line)
            if "time" in tpv and "altHAE" in tpv:
                reports.setdefault(tpv["time"][11:], tpv)
    return reports


@pytest.mark.parametrize("name, tolerance_deg", [
    ("ublox-zed-f9p-nmea.log", 1e-8),
    ("ublox-8.log", 1e-8),
    ("haicom-305N.log", 1e-8),  # gpsd moves its 2007 dates 1024 weeks on: compare times of day
    ("ublox-zed-f9p_hpg1.11.log", 1e-8),
    ("bundg_zeus_9.log", 5e-6),  # gpsd merges this boat's GLL (another position) into the same report
])
def test_gpsd_captures_agree_with_gpsd_decoding(name, tolerance_deg, tmp_path):
    driver, fixes = feed(DATA / "gnss_gpsd" / name, tmp_path)
    assert parse_errors(driver.stats.decoder) == {}
    reports = first_tpv_with_altitude_by_time_of_day(DATA / "gnss_gpsd" / f"{name}.chk")
    matched = 0
    for fix in fixes:
        stamp = dt.datetime.fromtimestamp(fix.sensor_time_ns / 1e9, dt.UTC).strftime("%H:%M:%S.%f")[:-3] + "Z"
        tpv = reports.get(stamp)
        if tpv is None:
            continue
        matched += 1
        assert fix.latitude_deg == pytest.approx(tpv["lat"], abs=tolerance_deg)
        assert fix.longitude_deg == pytest.approx(tpv["lon"], abs=tolerance_deg)
        assert fix.altitude_m == pytest.approx(tpv["altHAE"], abs=1e-3)
    assert len(fixes) > 20
    assert matched >= min(len(fixes), len(reports)) - 1


def test_a_moving_boats_nmea_velocities_agree_with_its_fixes(tmp_path):
    """gpsd's B&G chartplotter capture (RMC, VTG, GGA at 1 Hz, ~3 m/s): each epoch's velocity from its RMC speed and
    course, stamped as its fix, against the central difference of the fixes around it."""
    driver, fixes = feed(DATA / "gnss_gpsd/bundg_zeus_9.log", tmp_path)
    velocities = driver.of(GNSS_VELOCITY)
    assert parse_errors(driver.stats.decoder) == {}
    assert len(velocities) == 146  # one an RMC (its VTG a duplicate), also in the 9 epochs the capture has no GGA of
    assert driver.stats.decoder["duplicate_velocity_epoch"] >= len(velocities) - 2
    by_time = {f.sensor_time_ns: f for f in fixes}
    assert sum(v.sensor_time_ns in by_time for v in velocities) >= len(fixes) - 1 > 130  # each fix's own stamp
    lat0 = fixes[0].latitude_deg
    metres_per_deg_east = math.radians(1.0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))

    def enu(f: GnssFix) -> tuple[float, float]:
        return f.longitude_deg * metres_per_deg_east, math.radians(f.latitude_deg) * EARTH_RADIUS_M

    second = 1_000_000_000
    residuals = []
    for v in velocities:
        before, after = by_time.get(v.sensor_time_ns - second), by_time.get(v.sensor_time_ns + second)
        if before is None or after is None:
            continue
        (e0, n0), (e1, n1) = enu(before), enu(after)
        residuals.append((v.velocity_enu_mps[0] - (e1 - e0) / 2, v.velocity_enu_mps[1] - (n1 - n0) / 2))
        assert v.velocity_enu_mps[2] == 0.0 and v.velocity_covariance[8] >= 1e4  # no vertical in NMEA
    assert len(residuals) > 120
    speeds = [math.hypot(*v.velocity_enu_mps[:2]) for v in velocities]
    assert 2.5 < sum(speeds) / len(speeds) < 3.5  # it sails
    for axis in (0, 1):
        errors = [r[axis] for r in residuals]
        assert abs(sum(errors) / len(errors)) < 0.05  # no bias, no sign or axis swap
        rms = math.sqrt(sum(e * e for e in errors) / len(errors))
        assert rms < 0.3  # 0.23 / 0.25 m/s (0.1 kn, 0.1 deg resolution; a boat in waves over 2 s)
        assert rms < 1.5 * math.sqrt(velocities[0].velocity_covariance[0])  # the stated sigma is not optimistic


@pytest.mark.parametrize("name", ["ublox-zed-f9p_hpg1.11.log", "ublox-8.log"])
def test_a_still_receivers_nmea_velocities_are_near_zero(name, tmp_path):
    """Static u-blox captures: an NMEA velocity every epoch, all within the stated sigma's reach of 0 (u-blox
    leaves the course empty when nearly still)."""
    driver, fixes = feed(DATA / "gnss_gpsd" / name, tmp_path)
    velocities = driver.of(GNSS_VELOCITY)
    assert parse_errors(driver.stats.decoder) == {}
    assert len(velocities) >= len(fixes) - 2
    times = {f.sensor_time_ns for f in fixes}
    assert sum(v.sensor_time_ns in times for v in velocities) >= len(fixes) - 2
    for v in velocities:
        assert math.hypot(*v.velocity_enu_mps[:2]) < 0.35
        sigma = math.sqrt(v.velocity_covariance[0])
        assert 0.25 <= sigma < 0.35  # 0.25 m/s, more without a course
