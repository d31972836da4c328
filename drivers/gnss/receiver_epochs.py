"""What the GNSS decoder's fix and velocity halves share: time units, how one receiver epoch is told apart from
another (to the millisecond) and how many recent epochs each remembers, and the row-major ENU covariances they give.
"""

from __future__ import annotations

import math

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000
RECENT_EPOCHS = 64  # epochs remembered as already given a fix (or a velocity): a repeat of one of them is dropped

Covariance = tuple[float, ...]
UNKNOWN_COVARIANCE: Covariance = (0.0,) * 9


def epoch_key(sensor_time_ns: int) -> int:
    """One receiver epoch's key: its time to the millisecond."""
    return round(sensor_time_ns / NS_PER_MS)


def covariance_diagonal(east: float, north: float, up: float) -> Covariance:
    """Row-major ENU covariance from three standard deviations (m -> m^2, m/s -> m^2/s^2)."""
    return covariance_of_variances(east**2, north**2, up**2)


def covariance_of_variances(east: float, north: float, up: float) -> Covariance:
    """Row-major ENU covariance from the three axes' variances."""
    return (east, 0.0, 0.0, 0.0, north, 0.0, 0.0, 0.0, up)


def covariance_from_ellipse(
    major_m: float, minor_m: float, orientation_deg: float, up_m: float
) -> Covariance:
    """Row-major ENU covariance (m^2) from an error ellipse: semi-axis sigmas, major axis in degrees from
    north towards east, and the vertical sigma."""
    s, c = math.sin(math.radians(orientation_deg)), math.cos(math.radians(orientation_deg))
    # major axis along (east, north) = (s, c); minor axis along (c, -s)
    ee = major_m**2 * s * s + minor_m**2 * c * c
    nn = major_m**2 * c * c + minor_m**2 * s * s
    en = (major_m**2 - minor_m**2) * s * c
    return (ee, en, 0.0, en, nn, 0.0, 0.0, 0.0, up_m**2)
