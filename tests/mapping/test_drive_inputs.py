"""From a simulated drive log to the reconstruction's inputs: trajectory, keyframes and Lidar ground; the ground
filter's trajectory height raster on a synthetic bend."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from daemon.log_format.reader import read_log
from daemon.log_format.writer import LogWriter
from daemon.spine.config import ConfigError, load_config
from daemon.spine.messages import GnssFix
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU, WHEEL_SPEEDS
from mapping.inputs.drive_inputs import fuse_log_trajectory, gnss_std_m, load_drive
from mapping.inputs.lidar_ground import TILE_CELLS, GroundFilter, TrajectoryGround, ground_points
from mapping.localization.trajectory import Trajectory
from mapping.offline.reconstruct_command import DriveTruth, config_from_logs
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


def test_the_car_configs_imu_bias_is_the_fusions_prior(drive):
    """The car config's accelerometer bias sigma reaches the fusion: the simulated car's 0.02 m/s^2 (its IMU's)
    holds the roll nearer the truth than the unknown-IMU default of 0.2 on the same log."""
    inputs, truth, out = drive
    held = {t: [] for t in (GNSS_FIX, GNSS_VELOCITY, IMU, WHEEL_SPEEDS)}
    for rec in read_log([out], topics=list(held)):
        held[rec.topic].append(rec.message)
    config = load_config(CONFIG)
    gnss = config.sensors.gnss.model_copy(update={"imu_accel_bias_sigma_mps2": 0.2})
    loose = config.model_copy(update={"sensors": config.sensors.model_copy(update={"gnss": gnss})})
    gt = np.load(out.with_name("city.gt.npz"))
    t = gt["trajectory_host_mono_ns"]

    def mean_abs_roll_deg(trajectory: Trajectory) -> float:
        ok = (t >= trajectory.times_ns[0]) & (t <= trajectory.times_ns[-1])
        _, quat = trajectory.interpolate(t[ok])
        error = Rotation.from_quat(quat).inv() * Rotation.from_quat(gt["trajectory_quaternion_xyzw"][ok])
        return abs(float(np.degrees(error.as_euler("xyz")[:, 0]).mean()))

    tight_roll = mean_abs_roll_deg(inputs.trajectory)
    loose_roll = mean_abs_roll_deg(fuse_log_trajectory(held[GNSS_FIX], held[IMU], held[WHEEL_SPEEDS], loose,
                                                       truth.origin, inputs.clocks, held[GNSS_VELOCITY]))
    assert tight_roll < loose_roll, (tight_roll, loose_roll)


def test_the_drive_carries_its_fixes_reported_accuracy(drive):
    inputs, _, _ = drive
    # the simulated receiver reports an RTK fix's 1.4 cm horizontal and 2 cm vertical (sim/sensors/gnss_sim.py)
    assert inputs.gnss_std_m == pytest.approx((0.014, 0.02), rel=0.01)


def test_fixes_without_a_known_covariance_give_no_accuracy():
    def fix(east: float, up: float, kind: int = 2) -> GnssFix:
        return GnssFix(position_covariance=(east, 0, 0, 0, east, 0, 0, 0, up), covariance_type=kind)

    assert gnss_std_m([fix(0.01, 0.04), fix(0.04, 0.09), fix(0.09, 0.16)]) == pytest.approx((0.2, 0.3))
    assert gnss_std_m([fix(0.0, 0.0, kind=0)]) is None  # covariance type unknown
    assert gnss_std_m([fix(0.0, 0.0), fix(np.nan, 0.04)]) is None  # none positive and finite
    assert gnss_std_m([]) is None


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
    # on the road surface (cars filtered out), within the range noise and the fused roll's error (this drive:
    # 2.5 cm at -0.08 deg since the start's prior pins the antenna, 3.5 cm at -0.23 deg before)
    assert np.mean(np.abs(dz)) < 0.03
    assert np.percentile(np.abs(dz), 99) < 0.15
    # each ground point's firing time (the pose refinement's Lidar registration re-places them with it): within
    # the drive, and the vehicle then within the ground filter's range of the point
    seconds = inputs.lidar_ground_times
    assert seconds.shape == (len(g),) and 0 <= seconds.min() and seconds.max() <= inputs.drive_s
    track = inputs.path
    at = np.stack([np.interp(seconds, track.times, track.positions[:, k]) for k in range(2)], 1)
    reach = np.linalg.norm(g[:, :2] - at, axis=1)
    assert reach.max() < GroundFilter().max_range_m + 1.0
    assert np.median(reach) > GroundFilter().min_range_m


def _bend_trajectory() -> Trajectory:
    """20 s along a 60 m-radius bend, climbing at 4 %, sampled at 100 Hz."""
    t = np.arange(0.0, 20.0, 0.01)
    angle = 10.0 * t / 60.0
    positions = np.column_stack([60.0 * np.sin(angle), 60.0 * (1 - np.cos(angle)), 0.4 * t + 1.5])
    quats = Rotation.from_euler("z", angle[:, None]).as_quat()
    return Trajectory(np.round(t * 1e9).astype(np.int64), positions, quats, 48.1, 11.5, 500.0)


def test_trajectory_ground_raster_holds_the_nearest_trajectory_height():
    """Each cell holds the height of the trajectory point nearest to it; past the trajectory's ends the road goes
    on at the ends' grade (4 % here: 60 cm over the corridor's 15 m, more than the ground filter's band)."""
    traj = _bend_trajectory()
    road = TrajectoryGround.of(traj, 1.5, corridor_half_width_m=15.0, cell_m=0.25)
    ground = traj.positions - [0.0, 0.0, 1.5]
    rng = np.random.default_rng(0)
    xy = ground[rng.integers(0, len(ground), 20_000), :2] + rng.uniform(-25, 25, (20_000, 2))
    xy = np.concatenate([xy, ground[[0, -1], :2].repeat(2_000, 0) + rng.uniform(-15, 15, (4_000, 2))])
    centres = (np.floor(xy / 0.25) + 0.5) * 0.25
    dist, idx = cKDTree(ground[:, :2]).query(centres)
    heights = road.height_at(xy)
    inside = dist < 15.0
    ends = inside & ((idx == 0) | (idx == len(ground) - 1))
    middle = inside & ~ends
    assert middle.sum() > 5_000 and (~inside).sum() > 5_000 and ends.sum() > 1_000
    np.testing.assert_allclose(heights[middle], ground[idx[middle], 2], atol=1e-5)
    angle = 10.0 * 19.99 / 60.0  # the bend's heading at its last point; its first is 0 (east)
    outward = np.where((idx[ends] == 0)[:, None], [[-1.0, 0.0]], [[np.cos(angle), np.sin(angle)]])
    beyond = np.maximum(((centres[ends] - ground[idx[ends], :2]) * outward).sum(1), 0.0)
    grade = np.where(idx[ends] == 0, -0.04, 0.04)  # climbing: the road falls behind its start, rises past its end
    np.testing.assert_allclose(heights[ends], ground[idx[ends], 2] + grade * beyond, atol=0.03)
    assert (heights[ends] - ground[idx[ends], 2]).max() > 0.4 and (heights[ends] - ground[idx[ends], 2]).min() < -0.4
    assert np.isnan(heights[~inside]).all()
    assert road.heights.shape[1:] == (TILE_CELLS, TILE_CELLS)
    assert (~np.isnan(road.heights)).any((1, 2)).all()  # only tiles holding part of the corridor are stored


def test_ground_filter_keeps_the_road_and_drops_a_car_on_it():
    traj = _bend_trajectory()
    road = TrajectoryGround.of(traj, 1.5, corridor_half_width_m=15.0)
    ground = traj.positions - [0.0, 0.0, 1.5]
    rng = np.random.default_rng(1)
    at = ground[rng.integers(0, len(ground), 30_000)]
    surface = at + np.column_stack([rng.uniform(-10, 10, (30_000, 2)), np.zeros(30_000)])
    surface[:, 2] = at[:, 2] + rng.normal(0.0, 0.01, 30_000)  # the road is level across, as the trajectory
    car_centre = ground[1500]
    car = car_centre + np.column_stack([rng.uniform(-2, 2, (3_000, 2)), rng.uniform(0.15, 1.5, 3_000)])
    beside = car_centre + np.column_stack([rng.uniform(-2, 2, (2_000, 2)), np.zeros(2_000)])  # road by the car
    far = at[:3_000] + np.column_stack([rng.uniform(-40, 40, (3_000, 2)), np.zeros(3_000)])
    far = far[cKDTree(ground[:, :2]).query(far[:, :2])[0] > 15.5]  # outside the corridor
    kept = ground_points(np.concatenate([surface, beside, car, far]), road, GroundFilter())
    assert len(kept) > 0.5 * len(surface)
    assert cKDTree(car).query(kept)[0].min() > 1e-6  # nothing of the car's body
    assert cKDTree(far).query(kept)[0].min() > 1e-6  # none of the points beyond the corridor
    dist = cKDTree(ground[:, :2]).query(kept[:, :2])[0]
    assert dist.max() < 15.0 + 0.25


def test_ground_filter_keeps_the_road_past_the_trajectory_end_on_a_grade():
    """The cameras map the road up to 12 m beyond where a drive ends: on the bend's 4 % climb that road is up to
    60 cm above the trajectory's last ground height, and its Lidar points are kept (all were dropped by the
    35 cm band when the raster held the last point's height there)."""
    traj = _bend_trajectory()
    road = TrajectoryGround.of(traj, 1.5, corridor_half_width_m=15.0)
    ground = traj.positions - [0.0, 0.0, 1.5]
    angle = 10.0 * 19.99 / 60.0
    forward, left = np.array([np.cos(angle), np.sin(angle)]), np.array([-np.sin(angle), np.cos(angle)])
    rng = np.random.default_rng(3)
    ahead, across = rng.uniform(8.0, 14.0, 20_000), rng.uniform(-4.0, 4.0, 20_000)
    xy = ground[-1, :2] + np.outer(ahead, forward) + np.outer(across, left)
    points = np.column_stack([xy, ground[-1, 2] + 0.04 * ahead + rng.normal(0.0, 0.005, len(ahead))])
    kept = ground_points(points, road, GroundFilter())  # at most one point per 10 cm voxel

    def cells(p: np.ndarray) -> set:  # the 0.5 m cells, in the road's own axes, that hold a point
        local = (p[:, :2] - ground[-1, :2]) @ np.column_stack([forward, left])
        return set(map(tuple, np.floor(local / 0.5).astype(int).tolist()))

    assert len(cells(kept)) > 0.95 * len(cells(points))


def test_ground_filter_keeps_a_curb_top_in_cells_that_straddle_the_curb():
    """A straight road with a 15 cm curb 3 m to its left, at an angle to the 0.5 m grid, so that many grid
    cells hold gutter and curb top: the curb top and the sidewalk behind it are kept (the Lidar detail needs
    them), as is the road."""
    t = np.arange(0.0, 10.0, 0.01)
    heading = np.radians(17.0)
    direction, left = np.array([np.cos(heading), np.sin(heading)]), np.array([-np.sin(heading), np.cos(heading)])
    positions = np.column_stack([np.outer(t * 5.0, direction), np.full(len(t), 1.5)])
    quats = Rotation.from_euler("z", np.full((len(t), 1), heading)).as_quat()
    traj = Trajectory(np.round(t * 1e9).astype(np.int64), positions, quats, 48.1, 11.5, 500.0)
    road = TrajectoryGround.of(traj, 1.5, corridor_half_width_m=15.0)
    rng = np.random.default_rng(2)
    along, across = rng.uniform(0, 50, 60_000), rng.uniform(-3, 6, 60_000)
    z = np.where(across > 3.0, 0.15, 0.0) + rng.normal(0.0, 0.005, len(along))
    points = np.column_stack([np.outer(along, direction) + np.outer(across, left), z])
    kept = ground_points(points, road, GroundFilter())
    side = kept[:, :2] @ left

    def density(lo: float, hi: float) -> float:  # kept points per metre of the band lo < across < hi
        return float(((side > lo) & (side < hi)).sum()) / (hi - lo)

    curb_edge, curb_far, road_band = density(3.0, 3.5), density(4.0, 6.0), density(-3.0, 2.5)
    # a 0.5 m cell holding gutter too no longer drops the curb top (0.46 before; what is still dropped lies
    # within ~15 cm of the curb, in the flat-patch cells that hold the face)
    assert curb_edge > 0.75 * curb_far
    assert road_band > 0.9 * curb_far
    assert np.abs(kept[side > 3.0, 2] - 0.15).max() < 0.05 and np.abs(kept[side < 3.0, 2]).max() < 0.05


def test_recorded_config_brings_its_lidar_metadata_or_asks_for_a_config(drive, tmp_path):
    _, _, log = drive
    config, config_path = config_from_logs([str(log)])
    assert (config_path.parent / config.sensors.lidar.metadata_file).read_text().startswith("{")
    bare = tmp_path / "no-lidar-metadata.mcap"
    with LogWriter(bare, load_config(CONFIG)):  # no config path: the Lidar's metadata file is not recorded
        pass
    with pytest.raises(ConfigError, match="no Lidar metadata.*pass --config"):
        config_from_logs([str(bare)])
