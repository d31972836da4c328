"""Fuses GNSS fixes, IMU samples and wheel speeds into a smooth 6-DoF trajectory in a local ENU frame.

An error-state Kalman filter runs the IMU strapdown mechanisation forward and updates at every GNSS fix
(position, optionally velocity, antenna lever arm) and at 20 Hz epochs with the wheel speeds interpolated
there (rear-axle speed with a scale-factor state, zero lateral velocity of the rear axle and zero vertical velocity
of the middle between the axles, optional yaw rate; a drive without wheel speeds, such as a GNSS/INS box alone,
keeps the zero lateral and vertical velocities);
a Rauch-Tung-Striebel pass then smooths the whole window backward, and poses come out at IMU rate. A
first pass over the first minute refines the initial state. States (19 errors): position, velocity,
attitude of the IMU frame (world-frame angles), accelerometer bias, gyro bias, wheel scale error,
IMU-to-vehicle misalignment.
"""

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.spine.local_frame import LocalFrame
from mapping.localization.error_state import (
    BA,
    BG,
    MU,
    N_STATES,
    TH,
    K,
    NavState,
    P,
    V,
    reference_point_prior,
)
from mapping.localization.navigation_math import gravity_enu, normal_gravity, skew, so3_exp
from mapping.localization.trajectory import Trajectory

CHI2_3DOF_9999 = 21.11  # 99.99 % quantile of chi-square with 3 degrees of freedom
CHI2_2DOF_9999 = 18.42
CHI2_1DOF_9999 = 15.14


@dataclass(frozen=True)
class GnssFixes:
    """GNSS fixes: WGS84 latitude/longitude (deg), ellipsoidal height (m), position covariance in ENU m^2."""

    times_ns: np.ndarray  # (N,) int64
    lat_deg: np.ndarray  # (N,)
    lon_deg: np.ndarray  # (N,)
    alt_m: np.ndarray  # (N,) height above the WGS84 ellipsoid
    position_cov_enu: np.ndarray  # (N, 3, 3)
    velocity_enu: np.ndarray | None = None  # (N, 3) m/s of the antenna; rows with NaN are not used
    velocity_cov_enu: np.ndarray | None = None  # (N, 3, 3), required with velocity_enu


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples in the IMU's own frame: specific force (gravity included, m/s^2) and angular rate (rad/s)."""

    times_ns: np.ndarray  # (N,) int64
    accel: np.ndarray  # (N, 3)
    gyro: np.ndarray  # (N, 3)


@dataclass(frozen=True)
class WheelSpeeds:
    """Wheel speeds in m/s, columns front-left, front-right, rear-left, rear-right (the rear pair is used:
    it moves without side slip); optional yaw rate."""

    times_ns: np.ndarray  # (N,) int64
    speeds: np.ndarray  # (N, 4)
    yaw_rate: np.ndarray | None = None  # (N,) rad/s about the vehicle z axis (up), NaN where missing


@dataclass(frozen=True)
class VehicleMounting:
    """Where the sensors sit on the vehicle; lever arms in the vehicle frame (x forward, y left, z up), m."""

    gnss_lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))  # antenna phase centre
    imu_lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rear_axle_lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))  # centre of the rear axle
    imu_to_vehicle: np.ndarray = field(default_factory=lambda: np.eye(3))  # rotates IMU-frame vectors
    # prior 1-sigma of the error of imu_to_vehicle about the vehicle x, y, z axes (rad); estimated online
    imu_misalignment_sigma: np.ndarray = field(default_factory=lambda: np.full(3, 1e-4))
    # front axle this far ahead of the rear: with all four wheels on the road the body pitches with the chord
    # between the axles, and the point that does not move up or down in the body frame is the middle between
    # them (on a crest or a sag the rear axle does, by pitch rate x half the wheel base); 0: the rear axle
    wheel_base_m: float = 0.0


@dataclass(frozen=True)
class FusionSettings:
    """Noise model and initial uncertainties (automotive MEMS IMU, CAN wheel speeds by default)."""

    gyro_noise: float = 2e-3  # rad/s/sqrt(Hz), angle random walk
    accel_noise: float = 0.03  # m/s^2/sqrt(Hz), velocity random walk
    gyro_bias_walk: float = 2e-5  # rad/s^2/sqrt(Hz)
    accel_bias_walk: float = 1e-3  # m/s^3/sqrt(Hz)
    gyro_bias_sigma: float = 0.01  # rad/s, initial
    accel_bias_sigma: float = 0.2  # m/s^2, initial
    wheel_speed_sigma: float = 0.05  # m/s, per sample
    wheel_scale_sigma: float = 0.03  # initial relative scale error of the wheel speeds
    wheel_scale_walk: float = 1e-4  # 1/sqrt(s)
    lateral_velocity_sigma: float = 0.1  # m/s, rear axle sideways (slip)
    vertical_velocity_sigma: float = 0.1  # m/s, rear axle up/down (suspension)
    yaw_rate_sigma: float = 0.01  # rad/s
    misalignment_walk: float = 1e-6  # rad/sqrt(s), keeps the smoother well conditioned
    initial_tilt_sigma: float = np.radians(3.0)  # roll/pitch from the accelerometer at the start
    initial_yaw_sigma: float = np.radians(15.0)  # heading from the first GNSS displacement
    initial_speed_sigma: float = 0.5  # m/s
    heading_baseline_m: float = 10.0  # GNSS displacement used to find the initial heading
    # The receivers' velocity 1-sigma is multiplied by this: their Doppler velocities come out of tracking loops
    # and filters, correlated over many epochs (an INS's velocity over seconds), while each epoch is taken here as
    # independent, which over-weights them by about the square root of the epochs they span. Measured (bench/
    # RESULTS.md, 2026-12-06, 5 simulated worlds and KITTI 0005): at x1 the fused roll error of the simulated
    # drives doubled (median |mean| 0.115 deg without velocities -> 0.20), at x3 0.106; on 0005 the heading error
    # vs its INS falls 4.0 -> 1.8 (x1) / 1.5 deg (x3), the camera-only map near the path from +10.7 cm above its
    # Velodyne ground to +4.4 (x1) / +4.6 cm (x3).
    gnss_velocity_sigma_scale: float = 3.0
    # The same for the fixes' position 1-sigma: their errors (multipath, atmosphere, an RTK base's wander, a
    # GNSS-aided INS's filter) run over many epochs, while each fix is taken as independent, so at x1 the track's
    # shape followed the fixes' slow errors rather than the velocities and the IMU. Measured (bench/RESULTS.md,
    # 2026-12-06): KITTI 0005 --poses fusion, the track against its INS 0.21 -> 0.03 m RMS, its length 1.2 % short
    # -> 0.01 %, camera-only held-out 14.83 -> 15.22 dB; five simulated worlds neutral (roll median 0.071 -> 0.073
    # deg, lateral 1 s RMS worst 0.029 -> 0.016 cm).
    gnss_position_sigma_scale: float = 3.0
    gate_chi2: float = CHI2_3DOF_9999  # GNSS and wheel innovations above this are rejected (and counted)
    update_rate_hz: float = 20.0  # Kalman epochs for the wheel speeds (plus one at every GNSS fix)
    wheel_max_gap_s: float = 0.1  # wheel speeds are interpolated to an epoch only across shorter gaps
    initial_pass_s: float = 60.0  # length of the first pass that refines the initial state (0: none)
    refined_tilt_sigma: float = np.radians(0.5)  # attitude uncertainty at the start of the full pass
    refined_yaw_sigma: float = np.radians(2.0)


@dataclass(frozen=True)
class FusionResult:
    """The smoothed trajectory and what the fusion learned and rejected along the way."""

    trajectory: Trajectory
    velocities_enu: np.ndarray  # (N, 3) of the reference point
    accel_bias: np.ndarray  # (3,) final smoothed estimate, IMU frame
    gyro_bias: np.ndarray  # (3,)
    wheel_scale: float  # measured wheel speed = (1 + wheel_scale) * true speed
    imu_to_vehicle: np.ndarray  # (3, 3) estimated mounting rotation
    counts: dict[str, int]  # measurements used / rejected by the innovation gate, per kind


def _specific_force_at_reference(imu: ImuSamples, lever_arm_imu: np.ndarray, seconds: np.ndarray) -> np.ndarray:
    """Removes the centripetal and tangential accelerations between the IMU and the reference point."""
    gyro = np.asarray(imu.gyro, dtype=np.float64)
    window = max(1, round(0.05 / float(np.median(np.diff(seconds)))))  # angular acceleration from a 50 ms
    kernel = np.ones(window) / window  # moving average of the gyro
    smooth = np.stack([np.convolve(gyro[:, k], kernel, mode="same") for k in range(3)], axis=1)
    angular_accel = np.gradient(smooth, seconds, axis=0)
    centripetal = np.cross(gyro, np.cross(gyro, lever_arm_imu))
    return np.asarray(imu.accel, dtype=np.float64) - np.cross(angular_accel, lever_arm_imu) - centripetal


def _epoch_times(gnss_ns: np.ndarray, end_ns: int, update_rate_hz: float) -> np.ndarray:
    """Kalman epochs (int64 ns): every GNSS fix plus a regular grid for the wheel speeds, all in (0, end]."""
    grid = np.round(np.arange(1, int(end_ns * 1e-9 * update_rate_hz) + 1) * (1e9 / update_rate_hz))
    times = np.unique(np.concatenate([gnss_ns, grid.astype(np.int64), [end_ns]]))
    return times[(times > 0) & (times <= end_ns)]


def _interpolate_with_gaps(times: np.ndarray, sample_t: np.ndarray, values: np.ndarray, max_gap: float):
    """Linear interpolation at `times`; NaN where the neighbouring samples are missing or too far apart."""
    if len(sample_t) < 2:
        return np.full(len(times), np.nan)
    after = np.searchsorted(sample_t, times)
    inside = (after > 0) & (after < len(sample_t))
    after = np.clip(after, 1, max(len(sample_t) - 1, 1))
    ok = inside & (sample_t[after] - sample_t[after - 1] <= max_gap) & np.isfinite(values[after]) & np.isfinite(
        values[after - 1])
    result = np.full(len(times), np.nan)
    result[ok] = np.interp(times[ok], sample_t, values)
    return result


def _initial_heading(gnss_enu, gnss_t, imu_t, yaw_rate, mounting, baseline_m) -> float:
    """Heading at the first fix from the rear axle's chord over the first `baseline_m`: the axle moves along the
    car's heading, and over an arc its chord points half the angle turned (the gyro's) ahead of the start's."""
    far = np.flatnonzero(np.linalg.norm(gnss_enu[:, :2] - gnss_enu[0, :2], axis=1) > baseline_m)
    if not len(far):
        return 0.0
    end = far[0]
    along = (imu_t >= gnss_t[0]) & (imu_t <= gnss_t[end])
    turned = float(np.trapezoid(yaw_rate[along], imu_t[along])) if np.count_nonzero(along) > 1 else 0.0
    arm = (np.asarray(mounting.gnss_lever_arm, float) - np.asarray(mounting.rear_axle_lever_arm, float))[:2]
    yaw = np.arctan2(*(gnss_enu[end, 1::-1] - gnss_enu[0, 1::-1]))
    for _ in range(3):  # the antenna sits beside and ahead of the axle: its chord differs while turning
        start, finish = yaw - 0.5 * turned, yaw + 0.5 * turned
        chord = (gnss_enu[end, :2] - _rotate(arm, finish)) - (gnss_enu[0, :2] - _rotate(arm, start))
        yaw = float(np.arctan2(chord[1], chord[0]))
    return yaw - 0.5 * turned


def _rotate(xy: np.ndarray, angle: float) -> np.ndarray:
    return np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]) @ xy


def _initial_state(gnss_enu, gnss_cov0, gnss_t, imu_t, force_ref, gyro, wheel_t, rear_speed, mounting, settings):
    """Attitude from gravity (less the car's own acceleration: along its track from the speeds, centripetal from
    the gyro) and the first GNSS displacement; returns x and its covariance with the first fix's error in the
    position block (reference_point_prior makes it the reference point's)."""
    start = gnss_t[0]
    first = (imu_t >= start) & (imu_t <= start + 0.5)
    if not np.any(first):
        first = np.arange(len(imu_t)) == min(np.searchsorted(imu_t, start), len(imu_t) - 1)
    force, rate = force_ref[first].mean(axis=0), gyro[first].mean(axis=0)
    if len(wheel_t):
        near = (wheel_t >= start) & (wheel_t <= start + 1.0)
        speed0 = float(np.interp(start, wheel_t, rear_speed))
        accel_forward = np.polyfit(wheel_t[near], rear_speed[near], 1)[0] if np.count_nonzero(near) > 2 else 0.0
    else:  # no wheel speeds: the speed of the first GNSS second (the first pass refines it and the tilt)
        near = gnss_t <= start + 1.0
        speed0 = (float(np.linalg.norm(np.polyfit(gnss_t[near], gnss_enu[near, :2], 1)[0]))
                  if np.count_nonzero(near) > 2 else 0.0)
        accel_forward = 0.0
    r_iv = np.asarray(mounting.imu_to_vehicle, dtype=np.float64).T
    forward_i = r_iv[:, 0]
    # a car starting in a bend feels v x yaw rate sideways: taken for gravity it tilts the start (0.44 m/s^2: 2.5 deg)
    up_i = force - accel_forward * forward_i - np.cross(rate, speed0 * forward_i)
    up_i /= np.linalg.norm(up_i)
    yaw = _initial_heading(gnss_enu, gnss_t, imu_t, gyro @ up_i, mounting, settings.heading_baseline_m)
    heading_i = forward_i - (forward_i @ up_i) * up_i
    heading_i /= np.linalg.norm(heading_i)
    body = np.column_stack([heading_i, np.cross(up_i, heading_i), up_i])
    world = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    r_wi = world @ body.T
    r_wv = r_wi @ r_iv
    x = NavState(p=gnss_enu[0] - r_wv @ mounting.gnss_lever_arm, v=r_wv[:, 0] * speed0, r_wi=r_wi,
                 ba=np.zeros(3), bg=np.zeros(3), k=0.0, r_iv=r_iv)
    sigmas = np.concatenate([np.zeros(3), np.full(3, settings.initial_speed_sigma),
                             [settings.initial_tilt_sigma, settings.initial_tilt_sigma, settings.initial_yaw_sigma],
                             np.full(3, settings.accel_bias_sigma), np.full(3, settings.gyro_bias_sigma),
                             [settings.wheel_scale_sigma], mounting.imu_misalignment_sigma])
    p0 = np.diag(sigmas ** 2)
    p0[P, P] = gnss_cov0
    return x, p0


@dataclass
class _Inputs:
    """The measurements, preprocessed: times in ns from the first GNSS fix, positions in ENU."""

    imu_ns: np.ndarray
    gyro: np.ndarray
    force_ref: np.ndarray  # specific force moved to the reference point, IMU axes
    gnss_ns: np.ndarray
    gnss_enu: np.ndarray
    gnss_cov: np.ndarray
    gnss_velocity: np.ndarray | None
    gnss_velocity_cov: np.ndarray | None
    wheel_t: np.ndarray  # seconds
    rear_speed: np.ndarray
    yaw_rate: np.ndarray | None
    l_gnss: np.ndarray
    wheel_points: np.ndarray  # (3, 3) vehicle frame: where the speed, the zero lateral, the zero vertical velocity hold
    g0: float


@dataclass
class _Smoothed:
    times_ns: np.ndarray  # relative to the first GNSS fix, excluding 0
    positions: np.ndarray
    r_wv: np.ndarray  # (N, 3, 3) vehicle -> ENU
    velocities: np.ndarray
    first: NavState
    final: NavState
    counts: dict[str, int]


def _smooth(inputs: _Inputs, x: NavState, p: np.ndarray, end_ns: int, settings: FusionSettings) -> _Smoothed:
    """The forward error-state Kalman filter from time 0 to end_ns, then the RTS pass backward."""
    x = x.copy()
    imu_ns, gyro, force_ref, gnss_ns = inputs.imu_ns, inputs.gyro, inputs.force_ref, inputs.gnss_ns
    gnss_enu, gnss_cov, wheel_t, rear_speed = inputs.gnss_enu, inputs.gnss_cov, inputs.wheel_t, inputs.rear_speed
    l_gnss, g0 = inputs.l_gnss, inputs.g0
    epochs_ns = _epoch_times(gnss_ns, end_ns, settings.update_rate_hz)
    epochs = epochs_ns * 1e-9
    gnss_at = {int(t): i for i, t in enumerate(gnss_ns)}
    epoch_speed = _interpolate_with_gaps(epochs, wheel_t, rear_speed, settings.wheel_max_gap_s)
    no_wheels = len(wheel_t) == 0
    epoch_yaw_rate = (np.full(len(epochs), np.nan) if inputs.yaw_rate is None else
                      _interpolate_with_gaps(epochs, wheel_t, np.asarray(inputs.yaw_rate, dtype=np.float64),
                                             settings.wheel_max_gap_s))

    # piecewise-constant IMU input: interval j = [imu_t[j], imu_t[j+1]] uses the mean of its two samples
    gyro_mid = 0.5 * (gyro[1:] + gyro[:-1])
    force_mid = 0.5 * (force_ref[1:] + force_ref[:-1])
    knots_ns = np.union1d(imu_ns[(imu_ns > 0) & (imu_ns < end_ns)], epochs_ns)
    knots = knots_ns * 1e-9
    segment_start = np.concatenate([[0], knots_ns[:-1]])
    segment_imu = np.clip(np.searchsorted(imu_ns, segment_start, side="right") - 1, 0, len(imu_ns) - 2)
    segment_dt = np.diff(np.concatenate([[0], knots_ns])) * 1e-9
    knot_epoch = np.searchsorted(epochs_ns, knots_ns) + 1  # the epoch that ends each knot's interval
    is_epoch = np.isin(knots_ns, epochs_ns)

    q_rate = np.zeros(N_STATES)
    q_rate[V] = settings.accel_noise ** 2
    q_rate[TH] = settings.gyro_noise ** 2
    q_rate[BA] = settings.accel_bias_walk ** 2
    q_rate[BG] = settings.gyro_bias_walk ** 2
    q_rate[K] = settings.wheel_scale_walk ** 2
    q_rate[MU] = settings.misalignment_walk ** 2
    wheel_noise = np.diag([settings.wheel_speed_sigma ** 2, settings.lateral_velocity_sigma ** 2,
                           settings.vertical_velocity_sigma ** 2])

    n_epochs = len(epochs) + 1
    priors: list[NavState] = [x.copy()]
    posts: list[NavState] = [x.copy()]
    gains = np.zeros((n_epochs, N_STATES, N_STATES))
    knot_p = np.zeros((len(knots), 3))
    knot_v = np.zeros((len(knots), 3))
    knot_r = np.zeros((len(knots), 3, 3))
    counts = {f"{kind}_{outcome}": 0 for kind in ("gnss_position", "gnss_velocity", "wheel", "yaw_rate",
                                                              "nonholonomic")
              for outcome in ("used", "rejected")}
    eye = np.eye(N_STATES)
    sum_force = np.zeros(3)  # integral of the specific force in ENU over the epoch interval
    sum_rotation = np.zeros((3, 3))  # integral of the IMU attitude over the epoch interval
    interval = 0.0
    gravity = gravity_enu(x.p, g0)  # refreshed every epoch

    def update(residual, h, noise, gate, kind):
        nonlocal p
        s = h @ p @ h.T + noise
        gain_t = np.linalg.solve(s, h @ p)
        if residual @ np.linalg.solve(s, residual) > gate:
            counts[kind + "_rejected"] += 1
            return
        x.inject(gain_t.T @ residual)
        p = p - gain_t.T @ (h @ p)
        p = 0.5 * (p + p.T)
        counts[kind + "_used"] += 1

    for s_index in range(len(knots)):
        dt = segment_dt[s_index]
        j = segment_imu[s_index]
        w = gyro_mid[j] - x.bg
        r_new = x.r_wi @ so3_exp(w * dt)
        r_mid = 0.5 * (x.r_wi + r_new)
        f_world = r_mid @ (force_mid[j] - x.ba)
        v_new = x.v + (f_world + gravity) * dt
        x.p = x.p + 0.5 * (x.v + v_new) * dt
        x.v = v_new
        x.r_wi = r_new
        sum_force += f_world * dt
        sum_rotation += r_mid * dt
        interval += dt
        if not is_epoch[s_index]:
            knot_p[s_index], knot_v[s_index], knot_r[s_index] = x.p, x.v, x.r_wi
            continue

        epoch = knot_epoch[s_index]
        phi = eye.copy()  # second-order transition over the interval, world-frame attitude errors
        phi[P, V] = np.eye(3) * interval
        phi[V, TH] = -skew(sum_force)
        phi[P, TH] = -0.5 * interval * skew(sum_force)
        phi[V, BA] = -sum_rotation
        phi[P, BA] = -0.5 * interval * sum_rotation
        phi[TH, BG] = -sum_rotation
        phi[V, BG] = 0.5 * skew(sum_force) @ sum_rotation
        p_prev = p
        p = phi @ p @ phi.T + np.diag(q_rate * interval)
        gains[epoch] = np.linalg.solve(p, phi @ p_prev).T
        priors.append(x.copy())
        sum_force[:] = 0.0
        sum_rotation[:] = 0.0
        interval = 0.0
        w_vehicle = x.r_iv.T @ w

        i = gnss_at.get(int(knots_ns[s_index]))
        if i is not None:
            r_wv = x.r_wi @ x.r_iv
            lever_world = r_wv @ l_gnss
            h = np.zeros((3, N_STATES))
            h[:, P] = np.eye(3)
            h[:, TH] = -skew(lever_world)
            h[:, MU] = -r_wv @ skew(l_gnss)
            update(gnss_enu[i] - (x.p + lever_world), h, gnss_cov[i], settings.gate_chi2, "gnss_position")
            if inputs.gnss_velocity is not None and np.all(np.isfinite(inputs.gnss_velocity[i])):
                r_wv = x.r_wi @ x.r_iv
                arm_velocity = r_wv @ (skew(w_vehicle) @ l_gnss)
                h = np.zeros((3, N_STATES))
                h[:, V] = np.eye(3)
                h[:, TH] = -skew(arm_velocity)
                update(inputs.gnss_velocity[i] - (x.v + arm_velocity), h, inputs.gnss_velocity_cov[i],
                       settings.gate_chi2, "gnss_velocity")

        speed = epoch_speed[epoch - 1]
        if np.isfinite(speed) or no_wheels:  # the wheels' velocity in the vehicle frame
            r_wv = x.r_wi @ x.r_iv
            u_center = r_wv.T @ x.v
            u = u_center + np.diag(np.cross(w_vehicle, inputs.wheel_points))  # row k: point k's component k
            h = np.zeros((3, N_STATES))
            h[:, V] = r_wv.T
            h[:, TH] = r_wv.T @ skew(x.v)
            h[:, BG] = np.array([skew(arm)[k] for k, arm in enumerate(inputs.wheel_points)]) @ x.r_iv.T
            h[:, MU] = skew(u_center)
            if np.isfinite(speed):
                h[0] *= 1.0 + x.k
                h[0, K] = u[0]
                predicted = np.array([(1.0 + x.k) * u[0], u[1], u[2]])
                update(np.array([speed, 0.0, 0.0]) - predicted, h, wheel_noise, settings.gate_chi2, "wheel")
            else:  # no wheel speeds at all: the car still moves without sliding sideways or up
                update(-u[1:], h[1:], wheel_noise[1:, 1:], CHI2_2DOF_9999, "nonholonomic")

        yaw_rate = epoch_yaw_rate[epoch - 1]
        if np.isfinite(yaw_rate):
            h = np.zeros((1, N_STATES))
            h[0, BG] = -x.r_iv.T[2]
            h[0, MU] = skew(w_vehicle)[2]
            update(np.array([yaw_rate - w_vehicle[2]]), h, np.array([[settings.yaw_rate_sigma ** 2]]),
                   CHI2_1DOF_9999, "yaw_rate")
        posts.append(x.copy())
        gravity = gravity_enu(x.p, g0)
        knot_p[s_index], knot_v[s_index], knot_r[s_index] = x.p, x.v, x.r_wi

    smoothed = [posts[-1]]
    for k in range(n_epochs - 2, -1, -1):
        state = posts[k].copy()
        state.inject(gains[k + 1] @ smoothed[-1].minus(priors[k + 1]))
        smoothed.append(state)
    smoothed.reverse()

    # between epochs the forward IMU solution carries the detail; the smoother's correction is
    # interpolated linearly from the interval's start (after the update) to its end (before the update)
    correction_start = np.array([smoothed[k].minus(posts[k]) for k in range(n_epochs)])  # the last is zero
    correction_end = np.array([smoothed[k].minus(priors[k]) for k in range(1, n_epochs)] + [np.zeros(N_STATES)])
    epoch_start = np.concatenate([[0.0], epochs[:-1]])
    interval_index = knot_epoch - 1
    fraction = (knots - epoch_start[interval_index]) / (epochs - epoch_start)[interval_index]
    fraction[is_epoch] = 0.0  # an epoch knot holds the state after its update: the next interval's start
    interval_index[is_epoch] += 1
    correction = (correction_start[interval_index] * (1.0 - fraction[:, None])
                  + correction_end[interval_index] * fraction[:, None])
    r_iv = np.array([s.r_iv for s in smoothed])[interval_index]
    r_wv = Rotation.from_rotvec(correction[:, TH]).as_matrix() @ knot_r @ r_iv
    return _Smoothed(times_ns=knots_ns, positions=knot_p + correction[:, P], r_wv=r_wv,
                     velocities=knot_v + correction[:, V], first=smoothed[0], final=smoothed[-1], counts=counts)


def fuse_trajectory(gnss: GnssFixes, imu: ImuSamples, wheels: WheelSpeeds | None,
                    mounting: VehicleMounting = VehicleMounting(),
                    settings: FusionSettings = FusionSettings(),
                    origin: LocalFrame | None = None) -> FusionResult:
    """Forward error-state Kalman filter over the IMU, then an RTS smoother; poses come out at every IMU
    sample and Kalman epoch, from the first GNSS fix to the last IMU sample. The ENU origin defaults to
    the first GNSS fix. Without wheel speeds (None) the rear axle's zero lateral and vertical velocity is
    kept at every epoch instead."""
    wheels = wheels if wheels is not None else WheelSpeeds(np.zeros(0, np.int64), np.zeros((0, 4)))
    for name, times in (("gnss", gnss.times_ns), ("imu", imu.times_ns), ("wheel", wheels.times_ns)):
        if (name != "wheel" or len(times)) and (len(times) < 2 or np.any(np.diff(np.asarray(times, np.int64)) <= 0)):
            raise ValueError(f"{name} times must be at least 2 and strictly increasing")
    frame = origin or LocalFrame(float(gnss.lat_deg[0]), float(gnss.lon_deg[0]), float(gnss.alt_m[0]))
    t_ref = int(gnss.times_ns[0])
    imu_ns = np.asarray(imu.times_ns, dtype=np.int64) - t_ref
    gnss_ns = np.asarray(gnss.times_ns, dtype=np.int64) - t_ref
    imu_t, gnss_t = imu_ns * 1e-9, gnss_ns * 1e-9
    wheel_t = (np.asarray(wheels.times_ns, dtype=np.int64) - t_ref) * 1e-9
    gnss_enu = frame.geodetic_to_enu(gnss.lat_deg, gnss.lon_deg, gnss.alt_m)
    gnss_cov = np.asarray(gnss.position_cov_enu, dtype=np.float64) * settings.gnss_position_sigma_scale ** 2
    rear_speed = np.asarray(wheels.speeds, dtype=np.float64)[:, 2:4].mean(axis=1)
    r_vi_prior = np.asarray(mounting.imu_to_vehicle, dtype=np.float64)
    lever_imu = r_vi_prior.T @ np.asarray(mounting.imu_lever_arm, dtype=np.float64)
    force_ref = _specific_force_at_reference(imu, lever_imu, imu_t)
    gyro = np.asarray(imu.gyro, dtype=np.float64)
    l_gnss = np.asarray(mounting.gnss_lever_arm, dtype=np.float64)
    l_axle = np.asarray(mounting.rear_axle_lever_arm, dtype=np.float64)
    g0 = normal_gravity(frame.lat_deg, frame.alt_m)

    inputs = _Inputs(imu_ns=imu_ns, gyro=gyro, force_ref=force_ref, gnss_ns=gnss_ns, gnss_enu=gnss_enu,
                     gnss_cov=gnss_cov, gnss_velocity=gnss.velocity_enu,
                     gnss_velocity_cov=None if gnss.velocity_cov_enu is None else
                     np.asarray(gnss.velocity_cov_enu) * settings.gnss_velocity_sigma_scale ** 2,
                     wheel_t=wheel_t, rear_speed=rear_speed, yaw_rate=wheels.yaw_rate, l_gnss=l_gnss, g0=g0,
                     wheel_points=np.array([l_axle, l_axle, l_axle + [0.5 * mounting.wheel_base_m, 0.0, 0.0]]))
    x, p_antenna = _initial_state(gnss_enu, gnss_cov[0], gnss_t, imu_t, force_ref, gyro, wheel_t, rear_speed,
                                  mounting, settings)
    if settings.initial_pass_s > 0.0:
        # a first pass over the start of the drive finds the initial heading, tilt and biases, so the
        # full pass starts near the truth and its linearisation holds from the first second
        x = _smooth(inputs, x, reference_point_prior(p_antenna, x, l_gnss),
                    min(int(imu_ns[-1]), int(settings.initial_pass_s * 1e9)), settings).first
        p_antenna[TH, TH] = np.diag([settings.refined_tilt_sigma, settings.refined_tilt_sigma,
                                     settings.refined_yaw_sigma]) ** 2
    smoothed = _smooth(inputs, x, reference_point_prior(p_antenna, x, l_gnss), int(imu_ns[-1]), settings)
    knots_ns, counts = smoothed.times_ns, smoothed.counts
    first = smoothed.first
    times_ns = t_ref + np.concatenate([[0], knots_ns])
    positions = np.concatenate([[first.p], smoothed.positions])
    r_wv = np.concatenate([[first.r_wi @ first.r_iv], smoothed.r_wv])
    trajectory = Trajectory(times_ns=times_ns, positions=positions,
                            quaternions=Rotation.from_matrix(r_wv).as_quat(), origin_lat_deg=frame.lat_deg,
                            origin_lon_deg=frame.lon_deg, origin_alt_m=frame.alt_m)
    final = smoothed.final
    return FusionResult(trajectory=trajectory, velocities_enu=np.concatenate([[first.v], smoothed.velocities]),
                        accel_bias=final.ba, gyro_bias=final.bg, wheel_scale=final.k,
                        imu_to_vehicle=final.r_iv.T, counts=counts)
