"""The strapdown mechanisation's arithmetic: skew matrices, SO(3) exponential and logarithm, WGS84 normal gravity."""

import math

import numpy as np

from daemon.spine.local_frame import WGS84_A


def skew(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues), in scalar arithmetic for speed."""
    x, y, z = phi.tolist()
    angle2 = x * x + y * y + z * z
    if angle2 < 1e-12:
        s, c = 1.0, 0.5
    else:
        angle = math.sqrt(angle2)
        s, c = math.sin(angle) / angle, (1.0 - math.cos(angle)) / angle2
    return np.array([[1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y],
                     [c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x],
                     [c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)]])


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix with an angle well below pi (corrections, increments)."""
    vee = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    cos_angle = min(1.0, max(-1.0, 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)))
    angle = math.acos(cos_angle)
    return vee * (0.5 if angle < 1e-6 else 0.5 * angle / math.sin(angle))


def normal_gravity(lat_deg: float, alt_m: float) -> float:
    """Somigliana's normal gravity on the WGS84 ellipsoid with the free-air height correction, m/s^2."""
    s2 = np.sin(np.radians(lat_deg)) ** 2
    g0 = 9.7803253359 * (1.0 + 0.00193185265241 * s2) / np.sqrt(1.0 - 0.00669437999013 * s2)
    return float(g0 * (1.0 - 2.0 * alt_m / WGS84_A))


def gravity_enu(position: np.ndarray, g0: float) -> np.ndarray:
    """Gravity in the tangent frame near its origin: tilted towards the origin, weaker with height."""
    return -g0 * np.array([position[0] / WGS84_A, position[1] / WGS84_A, 1.0 - 2.0 * position[2] / WGS84_A])
