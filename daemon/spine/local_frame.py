"""WGS84 geodetic <-> ECEF <-> a local East-North-Up frame tangent to the ellipsoid at an origin (not UTM)."""

from dataclasses import dataclass, field

import numpy as np

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """Latitude and longitude in degrees, ellipsoidal height in metres -> ECEF metres, shape (..., 3)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack([(n + alt_m) * np.cos(lat) * np.cos(lon),
                     (n + alt_m) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - WGS84_E2) + alt_m) * np.sin(lat)], axis=-1)


def ecef_to_geodetic(ecef) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF metres (..., 3) -> (lat_deg, lon_deg, alt_m); Bowring's iteration (nm-exact)."""
    x, y, z = np.moveaxis(np.asarray(ecef, dtype=np.float64), -1, 0)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(5):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        alt = p * np.cos(lat) + z * np.sin(lat) - WGS84_A ** 2 / n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + alt)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    alt = p * np.cos(lat) + z * np.sin(lat) - WGS84_A ** 2 / n
    return np.degrees(lat), np.degrees(np.arctan2(y, x)), alt


def ecef_to_enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """3x3 matrix whose rows are the east, north and up unit vectors (in ECEF) at a geodetic point."""
    sl, cl = np.sin(np.radians(lat_deg)), np.cos(np.radians(lat_deg))
    so, co = np.sin(np.radians(lon_deg)), np.cos(np.radians(lon_deg))
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


@dataclass(frozen=True)
class LocalFrame:
    """An ENU tangent frame: x east, y north, z up, origin at a geodetic point (deg, ellipsoidal m)."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    origin_ecef: np.ndarray = field(init=False, repr=False, compare=False)
    ecef_to_enu_matrix: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin_ecef", geodetic_to_ecef(self.lat_deg, self.lon_deg, self.alt_m))
        object.__setattr__(self, "ecef_to_enu_matrix", ecef_to_enu_rotation(self.lat_deg, self.lon_deg))

    def ecef_to_enu(self, ecef) -> np.ndarray:
        return (np.asarray(ecef, dtype=np.float64) - self.origin_ecef) @ self.ecef_to_enu_matrix.T

    def enu_to_ecef(self, enu) -> np.ndarray:
        return np.asarray(enu, dtype=np.float64) @ self.ecef_to_enu_matrix + self.origin_ecef

    def geodetic_to_enu(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        return self.ecef_to_enu(geodetic_to_ecef(lat_deg, lon_deg, alt_m))

    def enu_to_geodetic(self, enu) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return ecef_to_geodetic(self.enu_to_ecef(enu))
