"""Pose fusion against the roadlog simulator's own motion (sim/world/ego_trajectory.py: four wheels on a random
world's surface, the body pitched with the chord between the axles): exact GNSS, IMU and wheel speeds give the
true roll and pitch, the first fix's sideways error does not become a roll, and the accelerometer bias prior bounds
the roll that noisy fixes move."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from daemon.spine.config import load_config
from daemon.spine.local_frame import LocalFrame
from mapping.localization.navigation_math import normal_gravity
from mapping.localization.pose_fusion import (
    FusionSettings,
    GnssFixes,
    ImuSamples,
    VehicleMounting,
    WheelSpeeds,
    fuse_trajectory,
)
from sim.sensors import can_sim, imu_sim
from sim.world.ego_trajectory import GRAVITY, drive_trajectory, specific_force_body
from sim.world.random_world import draw_scenario
from sim.world.road_world import build_world
from tests.daemon_fixtures import REPO

SECONDS = 8.0
T0_NS = 10**12


@pytest.fixture(scope="module")
def world_7():
    """Random world 7: it starts in a bend (0.08 rad/s at 12.9 m/s) into a sag (pitch -0.5 -> +3 deg)."""
    config = load_config(REPO / "configs" / "sim.yaml")
    scenario = draw_scenario(7, [c.name for c in config.sensors.cameras])
    ego = drive_trajectory(build_world(scenario, 7), config.vehicle, SECONDS, np.random.default_rng([7, 2]))
    origin = LocalFrame(scenario.origin.latitude_deg, scenario.origin.longitude_deg, scenario.origin.altitude_m)
    return config, ego, origin


def exact_inputs(config, ego, origin, first_fix_offset=(0.0, 0.0, 0.0)):
    ns = lambda t: np.round(t * 1e9).astype(np.int64) + T0_NS  # noqa: E731
    t_imu, t_gnss = np.arange(0.003, SECONDS, 0.01), np.arange(0.0, SECONDS, 0.1)
    t_wheel = np.arange(0.007, SECONDS, 0.02)
    lever = np.array(config.sensors.gnss.antenna_lever_arm_m)
    rot, pos = ego.pose(t_gnss)
    antenna = pos + np.einsum("nij,j->ni", rot, lever)
    antenna[0] += first_fix_offset
    # the fusion's gravity is the normal gravity where the world lies (the simulator's is the standard one)
    g_local = normal_gravity(origin.lat_deg, origin.alt_m)
    force = specific_force_body(ego, t_imu) + (g_local - GRAVITY) * ego.sample("rotation", t_imu)[:, 2, :]
    noise = can_sim.SPEED_NOISE, can_sim.YAW_NOISE
    can_sim.SPEED_NOISE = can_sim.YAW_NOISE = 0.0
    try:
        speeds, yaw = can_sim.wheel_speeds(ego, config.vehicle, t_wheel, np.random.default_rng(0))
    finally:
        can_sim.SPEED_NOISE, can_sim.YAW_NOISE = noise
    gnss = GnssFixes(ns(t_gnss), *origin.enu_to_geodetic(antenna),
                     np.tile(np.diag([0.014 ** 2, 0.014 ** 2, 0.02 ** 2]), (len(t_gnss), 1, 1)))
    return gnss, ImuSamples(ns(t_imu), force, ego.sample("body_rate", t_imu)), WheelSpeeds(ns(t_wheel), speeds, yaw)


def roll_pitch_errors_deg(result, ego) -> np.ndarray:
    """(N, 2) fused minus true roll and pitch at the fused trajectory's times."""
    traj = result.trajectory
    _, quat = traj.interpolate(traj.times_ns)
    fused = Rotation.from_quat(quat).as_euler("ZYX", degrees=True)
    true = Rotation.from_matrix(ego.sample("rotation", (traj.times_ns - T0_NS) * 1e-9)).as_euler("ZYX", degrees=True)
    return ((fused - true + 180.0) % 360.0 - 180.0)[:, [2, 1]]


def mounting(config, wheel_base_m):
    return VehicleMounting(gnss_lever_arm=np.array(config.sensors.gnss.antenna_lever_arm_m),
                           rear_axle_lever_arm=np.array(config.vehicle.rear_axle_m), wheel_base_m=wheel_base_m)


def test_exact_simulated_motion_gives_the_true_roll_and_pitch_with_the_vertical_constraint_between_the_axles(world_7):
    config, ego, origin = world_7
    gnss, imu, wheels = exact_inputs(config, ego, origin)
    between = np.abs(roll_pitch_errors_deg(fuse_trajectory(gnss, imu, wheels, mounting(config, 2.8), origin=origin),
                                           ego))
    assert between.max(axis=0).tolist() < [0.02, 0.02], between.max(axis=0)
    # at the rear axle the sag's pitch rate x half the wheel base reads as a tilt: what the fusion did before
    at_axle = np.abs(roll_pitch_errors_deg(fuse_trajectory(gnss, imu, wheels, mounting(config, 0.0), origin=origin),
                                           ego))
    assert at_axle[:, 0].mean() > 0.05 and at_axle[:, 1].max() > 0.05, at_axle.max(axis=0)


def test_the_first_fixs_sideways_error_does_not_become_a_roll(world_7):
    config, ego, origin = world_7
    heading = ego.sample("rotation", np.array([0.0]))[0]
    gnss, imu, wheels = exact_inputs(config, ego, origin, first_fix_offset=heading @ [0.0, 0.012, 0.0])
    errors = roll_pitch_errors_deg(fuse_trajectory(gnss, imu, wheels, mounting(config, 2.8), origin=origin), ego)
    # held independent of the attitude, 12 mm through the 1.2 m high antenna was a constant ~0.5 deg roll
    assert np.abs(errors[:, 0]).max() < 0.05, np.abs(errors).max(axis=0)


def test_the_accelerometer_bias_prior_bounds_the_roll_that_noisy_fixes_move(world_7):
    """World 7 turns 9 deg in 8 s: too little to tell a roll from a sideways accelerometer bias (both tilt the
    measured gravity). White fix noise of the reported 1.4 cm then moves that pair through the 1.2 m high antenna,
    by up to its prior: 0.2 m/s^2 (the default) let the roll go 0.10-0.18 deg over three noise draws, the simulated
    IMU's own 0.02 held it to 0.004-0.025 deg."""
    config, ego, origin = world_7
    gnss, imu, wheels = exact_inputs(config, ego, origin)
    antenna = origin.geodetic_to_enu(gnss.lat_deg, gnss.lon_deg, gnss.alt_m)
    loose, tight = [], []
    for seed in range(3):
        noise = np.random.default_rng(seed).normal(0.0, 0.014, (len(gnss.times_ns), 3))
        noisy = GnssFixes(gnss.times_ns, *origin.enu_to_geodetic(antenna + noise), gnss.position_cov_enu)
        for sigma, out in ((0.2, loose), (imu_sim.ACCEL_BIAS, tight)):
            result = fuse_trajectory(noisy, imu, wheels, mounting(config, 2.8), origin=origin,
                                     settings=FusionSettings(accel_bias_sigma=sigma))
            out.append(abs(roll_pitch_errors_deg(result, ego)[:, 0].mean()))
    assert max(tight) < 0.03, tight
    assert np.median(loose) > 3 * np.median(tight), (loose, tight)


def test_the_simulated_car_states_its_imu_bias():
    """configs/sim.yaml gives the fusion the simulated IMU's accelerometer bias sigma, as a user gives their IMU's
    datasheet value; a car config that does not state one keeps the conservative 0.2 m/s^2."""
    assert load_config(REPO / "configs" / "sim.yaml").sensors.gnss.imu_accel_bias_sigma_mps2 == imu_sim.ACCEL_BIAS
    assert load_config(REPO / "configs" / "car.yaml").sensors.gnss.imu_accel_bias_sigma_mps2 == 0.2
