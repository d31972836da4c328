"""The occlusion test of views without masks (mapping.fits.lidar_occlusion): what the Lidar saw standing on the
road hides the surface behind it, not the surface in front or beside; on a simulated drive it finds the cars the
masks mark and leaves the road."""

import numpy as np
import pytest

from daemon.spine.config import load_config
from daemon.spine.mapper_config import MasklessConfig
from daemon.spine.semantic_classes import SemanticClass
from mapping.fits.lidar_occlusion import OcclusionTest
from mapping.fits.vertex_observations import project_points
from mapping.inputs.drive_inputs import load_drive
from mapping.inputs.lidar_ground import TrajectoryGround, standing_points
from mapping.localization.trajectory import Trajectory
from mapping.method.road_map import WindowIndex
from mapping.method.road_mesh import build_road_mesh
from mapping.method.scene_data import CameraModel, Keyframe, StandingPoints
from mapping.offline.reconstruct_command import DriveTruth
from tests.daemon_fixtures import REPO

CAMERA = CameraModel("cam", np.array([[400.0, 0, 320], [0, 400, 180], [0, 0, 1]]), (0.0,) * 5, 640, 360)


def _view(time_s: float = 1.0) -> Keyframe:
    """A camera 1.5 m above the ground at the origin looking along +x (OpenCV axes: x right, y down, z ahead)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = [0.0, 0.0, 1.5]
    return Keyframe("cam", time_s, T, np.zeros((360, 640, 3), np.uint8), None)


def _car(x0: float, y0: float) -> np.ndarray:
    """Points on the near face and top of a 4 x 1.8 x 1.5 m box from (x0, y0 - 0.9) on the ground."""
    face = [(x0, y0 + dy, z) for dy in np.arange(-0.9, 0.91, 0.2) for z in np.arange(0.5, 1.51, 0.2)]
    top = [(x0 + dx, y0 + dy, 1.5) for dx in np.arange(0, 4.01, 0.2) for dy in np.arange(-0.9, 0.91, 0.2)]
    return np.array(face + top, np.float32)


def test_a_car_hides_the_road_behind_it_not_in_front_or_beside_it():
    standing = StandingPoints.of([(0.5, np.zeros((0, 3), np.float32)), (1.05, _car(10.0, 0.0))])
    test = OcclusionTest.of(standing, MasklessConfig())
    road = np.array([[14.0, 0.0, 0.0], [20.0, 0.5, 0.0], [7.0, 0.0, 0.0], [14.0, 5.0, 0.0], [11.0, -0.5, 0.0]])
    uv, ok = project_points(road, CAMERA, _view().T_world_camera)
    assert ok.all()
    hidden = test.hidden(_view(), CAMERA, uv, road)
    # behind the car (twice), in front of it, beside it, under it (behind its face)
    assert hidden.tolist() == [True, True, False, False, True]
    assert not test.hidden(_view(0.5), CAMERA, uv, road).any()  # the scan nearest in time saw nothing
    assert test.hidden(_view(2.0), CAMERA, uv, road) is None  # no scan within max_gap_s (0.25 s): not tested
    assert OcclusionTest.of(standing, MasklessConfig(lidar_occlusion=False)) is None
    assert OcclusionTest.of(None, MasklessConfig()) is None


def test_standing_points_are_what_stands_on_the_road_thinned_to_voxels():
    times = np.arange(0, 10_000_000_000, 100_000_000, dtype=np.int64)
    x = times / 1e9 * 5.0
    trajectory = Trajectory(times, np.stack([x, 0 * x, 0 * x + 0.5], 1), np.tile([0.0, 0, 0, 1], (len(x), 1)),
                            0.0, 0.0, 0.0)
    road = TrajectoryGround.of(trajectory, 0.5, 6.0)
    world = np.array([[10.0, 1.0, 0.1], [10.0, 1.0, 1.0], [10.05, 1.05, 1.02], [12.0, -2.0, 2.5], [12.0, 2.0, 4.0],
                      [12.0, 20.0, 1.0]])  # a curb, a car (twice in one voxel), a wall, a branch, off the corridor
    kept = standing_points(world, road, 0.4, 3.0)
    assert kept.dtype == np.float32 and kept.tolist() == world[[1, 3]].astype(np.float32).tolist()
    scans = StandingPoints.of([(0.0, kept[:1]), (0.2, kept[1:])])
    assert scans.nearest_scan(0.09, 0.25).tolist() == kept[:1].tolist()
    assert scans.nearest_scan(0.11, 0.25).tolist() == kept[1:].tolist()
    assert scans.nearest_scan(0.5, 0.25) is None and StandingPoints.of([]).nearest_scan(0.0, 1.0) is None


@pytest.fixture(scope="module")
def drive(city_drive):
    config = load_config(REPO / "configs" / "sim.yaml")
    truth = DriveTruth.load(city_drive.with_name("city.gt.npz"))
    return load_drive([city_drive], config, REPO / "configs" / "sim.yaml", origin=truth.origin, standing=True), config


def test_on_a_simulated_drive_it_hides_what_the_masks_call_obstacles_and_keeps_the_road(drive):
    inputs, config = drive
    assert inputs.lidar_standing is not None and len(inputs.lidar_standing.times) > 20  # every 2nd scan of 5 s
    mesh = build_road_mesh(inputs.path, config.mapper.mesh.corridor_half_width_m, 0.1,
                           config.vehicle.reference_height_m)
    windows, fast = WindowIndex.of(mesh), config.mapper.fast_fit
    test = OcclusionTest.of(inputs.lidar_standing, config.mapper.maskless)
    reads, hidden = np.zeros(256, np.int64), np.zeros(256, np.int64)
    for kf in inputs.keyframes[::3]:
        s = float(inputs.path.horizontal_distance_at(kf.timestamp))
        a, b = np.searchsorted(windows.vertex_s, [s - fast.behind_m, s + fast.ahead_m])
        ids = windows.vertex_order[a:b]
        points = np.concatenate([mesh.xy[ids], mesh.z0[ids, None]], 1)
        uv, ok = project_points(points, inputs.cameras[kf.camera], kf.T_world_camera)
        h = test.hidden(kf, inputs.cameras[kf.camera], uv[ok], points[ok])
        width = kf.semantics.shape[1]
        label = kf.semantics.reshape(-1)[np.rint(uv[ok, 1]).astype(int) * width + np.rint(uv[ok, 0]).astype(int)]
        reads += np.bincount(label, minlength=256)
        hidden += np.bincount(label[h], minlength=256)
    share = hidden / np.maximum(reads, 1)
    assert reads[SemanticClass.OBSTACLE] > 10_000 and reads[SemanticClass.ROAD] > 10_000  # cars in view
    assert share[SemanticClass.OBSTACLE] > 0.85  # the cars the masks mark (the masks' own errors aside)
    assert share[SemanticClass.ROAD] < 0.2 and share[SemanticClass.LANE_MARKING] < 0.2
