"""The simulated GNSS receiver: antenna fixes with RTK-like (cm) or stand-alone (m) errors, and the bytes a
u-blox receiver sends for each epoch: NMEA RMC, GGA, GST (pynmea2) and UBX NAV-PVT (pyubx2)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
import pynmea2
from pyubx2 import GET, UBXMessage

from daemon.spine.local_frame import LocalFrame
from sim.world.ego_trajectory import EgoTrajectory

GPS_EPOCH_UNIX_MS = 315_964_800_000
GPS_LEAP_SECONDS = 18
WEEK_MS = 604_800_000
KNOTS_PER_MPS = 1.0 / 0.514444


@dataclass(frozen=True)
class GnssErrorModel:
    white_h_m: float  # per-epoch noise, each horizontal axis
    white_v_m: float
    wander_h_m: float  # slowly wandering (Gauss-Markov) error
    wander_v_m: float
    wander_tau_s: float
    reported_h_m: float  # the receiver's own 1-sigma estimates
    reported_v_m: float
    velocity_m_s: float
    rtk: bool


ERROR_MODELS = {
    "rtk": GnssErrorModel(0.008, 0.012, 0.006, 0.01, 20.0, 0.014, 0.02, 0.02, True),
    "metre": GnssErrorModel(0.3, 0.5, 0.9, 1.4, 60.0, 1.2, 2.0, 0.08, False),
}


@dataclass(frozen=True)
class GnssEpoch:
    utc_ns: int
    latitude_deg: float
    longitude_deg: float
    height_m: float  # above the WGS84 ellipsoid
    velocity_enu: tuple[float, float, float]  # of the antenna, m/s
    h_acc_m: float
    v_acc_m: float
    rtk: bool
    num_sv: int = 21
    s_acc_m_s: float = 0.05  # the receiver's 1-sigma of each velocity axis


def _gauss_markov(n: int, dt_s: float, sigma: float, tau: float, rng: np.random.Generator) -> np.ndarray:
    a = np.exp(-dt_s / tau)
    e = rng.normal(0.0, sigma * np.sqrt(1 - a * a), n)
    out = np.empty(n)
    x = rng.normal(0.0, sigma)
    for i in range(n):
        x = a * x + e[i]
        out[i] = x
    return out


def antenna_epochs(ego: EgoTrajectory, frame: LocalFrame, lever_arm: np.ndarray, true_s: np.ndarray,
                   utc_ns: np.ndarray, quality: str, rng: np.random.Generator) -> list[GnssEpoch]:
    """Noisy fixes of the antenna (at `lever_arm` in the vehicle frame) at the given true times."""
    model = ERROR_MODELS[quality]
    n = len(true_s)
    rot, pos = ego.pose(true_s)
    antenna = pos + rot @ lever_arm
    dt_s = float(np.median(np.diff(true_s))) if n > 1 else 0.1
    error = np.column_stack([
        rng.normal(0, model.white_h_m, n) + _gauss_markov(n, dt_s, model.wander_h_m, model.wander_tau_s, rng),
        rng.normal(0, model.white_h_m, n) + _gauss_markov(n, dt_s, model.wander_h_m, model.wander_tau_s, rng),
        rng.normal(0, model.white_v_m, n) + _gauss_markov(n, dt_s, model.wander_v_m, model.wander_tau_s, rng),
    ])
    lat, lon, alt = frame.enu_to_geodetic(antenna + error)
    # the antenna's velocity: the reference point's and the turn's (body rate x lever arm, turned into ENU)
    swing = np.einsum("nij,nj->ni", rot, np.cross(ego.sample("body_rate", true_s), lever_arm))
    vel = ego.sample("velocity", true_s) + swing + rng.normal(0, model.velocity_m_s, (n, 3))
    return [GnssEpoch(int(utc_ns[i]), float(lat[i]), float(lon[i]), float(alt[i]), tuple(map(float, vel[i])),
                      model.reported_h_m, model.reported_v_m, model.rtk, s_acc_m_s=model.velocity_m_s)
            for i in range(n)]


def _nmea_angle(value: float, degree_digits: int) -> str:
    a = abs(value)
    degrees = int(a)
    minutes = (a - degrees) * 60.0
    return f"{degrees:0{degree_digits}d}{minutes:010.7f}"


def epoch_bytes(epoch: GnssEpoch) -> bytes:
    """RMC, GGA, GST and NAV-PVT for one epoch, as the receiver writes them."""
    when = dt.datetime.fromtimestamp(epoch.utc_ns / 1e9, dt.UTC)
    hhmmss = when.strftime("%H%M%S") + f".{when.microsecond // 10000:02d}"
    lat = _nmea_angle(epoch.latitude_deg, 2)
    lon = _nmea_angle(epoch.longitude_deg, 3)
    ns = "N" if epoch.latitude_deg >= 0 else "S"
    ew = "E" if epoch.longitude_deg >= 0 else "W"
    ve, vn, vu = epoch.velocity_enu
    speed = float(np.hypot(ve, vn))
    course = float(np.degrees(np.arctan2(ve, vn)) % 360.0)
    quality = "4" if epoch.rtk else "1"
    mode = "R" if epoch.rtk else "A"
    sentences = [
        pynmea2.RMC("GN", "RMC", (hhmmss, "A", lat, ns, lon, ew, f"{speed * KNOTS_PER_MPS:.3f}", f"{course:.2f}",
                                  when.strftime("%d%m%y"), "", "", mode)),
        pynmea2.GGA("GN", "GGA", (hhmmss, lat, ns, lon, ew, quality, f"{epoch.num_sv:02d}", "0.6",
                                  f"{epoch.height_m:.4f}", "M", "0.0", "M", "1.0" if epoch.rtk else "", "0000"
                                  if epoch.rtk else "")),
        pynmea2.GST("GN", "GST", (hhmmss, f"{epoch.h_acc_m:.3f}", f"{epoch.h_acc_m:.3f}", f"{epoch.h_acc_m:.3f}",
                                  "0.0", f"{epoch.h_acc_m:.3f}", f"{epoch.h_acc_m:.3f}", f"{epoch.v_acc_m:.3f}")),
    ]
    text = "".join(s.render() + "\r\n" for s in sentences).encode("ascii")
    itow = ((epoch.utc_ns // 1_000_000) - GPS_EPOCH_UNIX_MS + GPS_LEAP_SECONDS * 1000) % WEEK_MS
    pvt = UBXMessage(
        "NAV", "NAV-PVT", GET, iTOW=itow, year=when.year, month=when.month, day=when.day, hour=when.hour,
        min=when.minute, second=when.second, validDate=1, validTime=1, fullyResolved=1, tAcc=20,
        nano=epoch.utc_ns % 1_000_000_000, fixType=3,
        gnssFixOk=1, diffSoln=1 if epoch.rtk else 0, carrSoln=2 if epoch.rtk else 0, numSV=epoch.num_sv,
        lon=epoch.longitude_deg, lat=epoch.latitude_deg, height=round(epoch.height_m * 1000),
        hMSL=round(epoch.height_m * 1000), hAcc=round(epoch.h_acc_m * 1000), vAcc=round(epoch.v_acc_m * 1000),
        velN=round(vn * 1000), velE=round(ve * 1000), velD=round(-vu * 1000), gSpeed=round(speed * 1000),
        headMot=course, sAcc=round(epoch.s_acc_m_s * 1000), headAcc=1.0, pDOP=1.2)
    return text + pvt.serialize()
