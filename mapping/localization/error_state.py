"""The pose fusion's nominal state and the layout of its 19 errors: position, velocity, attitude of the IMU frame
(world-frame angles), accelerometer bias, gyro bias, wheel scale error, IMU-to-vehicle misalignment; an error
injected into a state, the error between two states, and the reference point's prior from the first GNSS fix."""

from dataclasses import dataclass

import numpy as np

from mapping.localization.navigation_math import skew, so3_exp, so3_log

P, V, TH, BA, BG, K, MU = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15), 15, slice(16, 19)
N_STATES = 19


@dataclass
class NavState:
    p: np.ndarray
    v: np.ndarray
    r_wi: np.ndarray  # IMU frame -> ENU
    ba: np.ndarray
    bg: np.ndarray
    k: float
    r_iv: np.ndarray  # vehicle frame -> IMU frame

    def copy(self) -> "NavState":
        return NavState(self.p.copy(), self.v.copy(), self.r_wi.copy(), self.ba.copy(), self.bg.copy(), self.k,
                        self.r_iv.copy())

    def inject(self, dx: np.ndarray) -> None:
        self.p = self.p + dx[P]
        self.v = self.v + dx[V]
        self.r_wi = so3_exp(dx[TH]) @ self.r_wi
        self.ba = self.ba + dx[BA]
        self.bg = self.bg + dx[BG]
        self.k = self.k + dx[K]
        self.r_iv = self.r_iv @ so3_exp(dx[MU])

    def minus(self, other: "NavState") -> np.ndarray:
        """Error vector dx such that other.inject(dx) gives self."""
        dx = np.empty(N_STATES)
        dx[P] = self.p - other.p
        dx[V] = self.v - other.v
        dx[TH] = so3_log(self.r_wi @ other.r_wi.T)
        dx[BA] = self.ba - other.ba
        dx[BG] = self.bg - other.bg
        dx[K] = self.k - other.k
        dx[MU] = so3_log(other.r_iv.T @ self.r_iv)
        return dx


def reference_point_prior(p_antenna: np.ndarray, x: NavState, gnss_lever_arm: np.ndarray) -> np.ndarray:
    """The initial covariance when the start's position is the first fix less the lever arm: `p_antenna` holds the
    fix's error in its position block, independent of the attitude. The fix pins the antenna, not the reference
    point: an attitude error turns the lever arm, so the reference point's error is the fix's plus the lever arm's
    turn, correlated with the attitude. (Held independent, the first fix's 8 mm sideways error became a constant
    0.4 deg roll through a 1.2 m high antenna: on a straight road a roll, a lateral accelerometer bias and a
    sideways shift together change no measurement.)"""
    r_wv = x.r_wi @ x.r_iv
    j = np.eye(N_STATES)  # error of the reference point = antenna's error + j[P] @ (attitude, misalignment errors)
    j[P, TH] = skew(r_wv @ gnss_lever_arm)
    j[P, MU] = r_wv @ skew(gnss_lever_arm)
    return j @ p_antenna @ j.T
