"""From a simulated drive log to the reconstruction's inputs: trajectory, keyframes and Lidar ground."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from daemon.config import load_config
from mapping.drive_inputs import load_drive
from mapping.reconstruct_command import DriveTruth
from tests.daemon_fixtures import REPO

CONFIG = REPO / "configs" / "sim.yaml"


@pytest.fixture(scope="module")
def drive(city_drive):
    out = city_drive
    config = load_config(CONFIG)
    truth = DriveTruth.load(out.with_name("city.gt.npz"))
    return load_drive([out], config, CONFIG, origin=truth.origin), truth, out


def test_clocks_are_recognised(drive):
    inputs, _, _ = drive
    kinds = {t: c.kind for t, c in inputs.clocks.items()}
    assert kinds["camera/front_wide"] == "host"
    assert kinds["gnss/fix"] == "utc" and kinds["lidar/packets"] == "utc"
    assert kinds["imu"] == "free"


def test_fused_trajectory_matches_the_truth(drive):
    inputs, _, out = drive
    gt = np.load(out.with_name("city.gt.npz"))
    t = gt["trajectory_host_mono_ns"]
    ok = (t >= inputs.trajectory.times_ns[0]) & (t <= inputs.trajectory.times_ns[-1])
    pos, quat = inputs.trajectory.interpolate(t[ok])
    err = pos - gt["trajectory_position_enu"][ok]
    assert np.sqrt((err[:, :2] ** 2).sum(1).mean()) < 0.05
    assert np.sqrt((err[:, 2] ** 2).mean()) < 0.03
    rot_err = Rotation.from_quat(quat).inv() * Rotation.from_quat(gt["trajectory_quaternion_xyzw"][ok])
    assert np.degrees(rot_err.magnitude()).mean() < 0.5


def test_keyframes_and_lidar_ground(drive):
    inputs, truth, _ = drive
    assert inputs.counts["keyframes"] >= 3 * 20  # every ~1 m, three cameras
    assert {k.camera for k in inputs.keyframes} == {"front_wide", "front_left", "front_right"}
    k = inputs.keyframes[0]
    assert k.image.shape[2] == 3 and k.semantics.shape == k.image.shape[:2]
    g = inputs.lidar_ground_points
    assert len(g) > 10_000
    e = truth.elevation
    j = np.round((g[:, 0] - e.origin_xy[0]) / e.resolution_m).astype(int)
    i = np.round((g[:, 1] - e.origin_xy[1]) / e.resolution_m).astype(int)
    inside = (i >= 0) & (i < e.elevation_m.shape[0]) & (j >= 0) & (j < e.elevation_m.shape[1])
    dz = g[inside, 2] - e.elevation_m[i[inside], j[inside]]
    dz = dz[np.isfinite(dz)]
    assert np.mean(np.abs(dz)) < 0.03  # on the road surface (cars filtered out), within the range noise
    assert np.percentile(np.abs(dz), 99) < 0.15
