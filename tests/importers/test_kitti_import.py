"""`roadlog import kitti-odometry|kitti-raw` on the real KITTI drives in ../shared/data, through the CLI, checked
against the dataset's own files (poses, calibration, PNG bytes, OXTS records)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from daemon.commands.cli import main as roadlog
from daemon.commands.log_info import summarise
from daemon.log_format.reader import read_log
from daemon.spine.local_frame import LocalFrame
from daemon.spine.point_cloud_codec import point_array
from daemon.spine.topics import POSE, camera_topic
from importers.kitti_raw import ins_positions, read_oxts
from mapping.inputs.drive_inputs import start_loading_drive
from mapping.offline.reconstruct_command import config_from_logs

DATA = Path("/work/shared/data")
ODOMETRY, RAW = DATA / "kitti_odometry_01", DATA / "kitti_raw_0005"


def imported(tmp_path: Path, capsys, *args: str) -> tuple[Path, dict]:
    out = tmp_path / "drive.mcap"
    assert roadlog(["import", *args, "--out", str(out)]) == 0
    return out, json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_kitti_odometry_imports_frames_and_ground_truth_poses(tmp_path, capsys):
    log, printed = imported(tmp_path, capsys, "kitti-odometry", str(ODOMETRY))
    assert printed["messages"] == {"pose": 51, "camera/image_0": 51} and printed["drive_s"] == pytest.approx(5.0)
    records = list(read_log([log]))
    frames = [r.message for r in records if r.topic == camera_topic("image_0")]
    assert [f.data for f in frames] == [p.read_bytes() for p in sorted((ODOMETRY / "image_0").glob("*.png"))]
    assert {f.format for f in frames} == {"png"}
    # KITTI's camera -> world(first camera) poses, seen with the car's axes: forward = camera z, left = -x, up = -y
    kitti = np.loadtxt(ODOMETRY / "poses.txt").reshape(-1, 3, 4)
    poses = [r.message for r in records if r.topic == POSE]
    positions = np.array([p.position_m for p in poses])
    np.testing.assert_allclose(positions, np.column_stack([kitti[:51, 2, 3], -kitti[:51, 0, 3], -kitti[:51, 1, 3]]),
                               atol=1e-9)
    assert 50 < np.linalg.norm(np.diff(positions, axis=0), axis=1).sum() < 54  # the ~52 m highway exit
    assert positions[-1, 1] < -35 and abs(positions[-1, 2]) < 1.5  # bending right, nearly level
    headings = Rotation.from_quat([p.orientation_xyzw for p in poses]).apply([1.0, 0.0, 0.0])
    camera_z = kitti[:51, :, 2]
    np.testing.assert_allclose(headings, np.column_stack([camera_z[:, 2], -camera_z[:, 0], -camera_z[:, 1]]),
                               atol=1e-6)  # KITTI's rotations have 7 digits: nearly, not exactly, orthonormal
    config, _ = config_from_logs([str(log)])
    (camera,) = config.sensors.cameras
    p0 = np.array(ODOMETRY.joinpath("calib.txt").read_text().split()[:12], float).reshape(3, 4)
    np.testing.assert_allclose(camera.intrinsics.matrix(), p0[:, :3])
    assert (camera.width, camera.height, camera.backend, config.vehicle.reference_height_m) == (1241, 376,
                                                                                                  "recorded", 1.65)
    info = summarise([str(log)])
    assert info["messages_per_topic"] == {"camera/image_0": 51, "pose": 51}
    assert "KITTI odometry" in info["recorded"]["source"] and info["recorded"]["cameras"]["image_0"]["width"] == 1241


def devkit_projection(points_velo: np.ndarray) -> np.ndarray:
    """KITTI's devkit: pixel = P_rect_02 @ R_rect_00 @ T_cam0_velo @ X_velo."""
    def values(name: str) -> dict[str, np.ndarray]:
        out = {}
        for line in (RAW / name).read_text().splitlines():
            key, _, rest = line.partition(":")
            try:
                out[key] = np.array(rest.split(), float)
            except ValueError:
                pass
        return out

    cam, velo = values("calib_cam_to_cam.txt"), values("calib_velo_to_cam.txt")
    r_rect = np.eye(4)
    r_rect[:3, :3] = cam["R_rect_00"].reshape(3, 3)
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = velo["R"].reshape(3, 3), velo["T"]
    h = cam["P_rect_02"].reshape(3, 4) @ r_rect @ t @ np.column_stack([points_velo, np.ones(len(points_velo))]).T
    return (h[:2] / h[2]).T


def test_kitti_raw_imports_frames_oxts_and_a_calibration_that_projects_like_the_devkit(tmp_path, capsys):
    log, printed = imported(tmp_path, capsys, "kitti-raw", str(RAW))
    assert {k: printed["messages"][k] for k in ("camera/image_02", "gnss/fix", "imu", "pose")} == {
        "camera/image_02": 91, "gnss/fix": 91, "imu": 91, "pose": 91}
    assert printed["drive_s"] == pytest.approx(9.3, abs=0.05) and printed["messages"]["lidar/points"] == 5
    config, _ = config_from_logs([str(log)])
    assert config.sensors.lidar.model == "point-cloud"
    clouds = [r.message for r in read_log([log], topics=["lidar/points"])]
    scan0 = np.fromfile(RAW / "velodyne_points/data/0000000000.bin", np.float32).reshape(-1, 4)
    cloud0 = point_array(clouds[0])
    np.testing.assert_array_equal(cloud0[:, :4], scan0)  # x, y, z, reflectance as KITTI gives them
    ahead = np.abs(np.degrees(np.arctan2(scan0[:, 1], scan0[:, 0]))) < 2.0
    span_s = (clouds[0].host_mono_ns - clouds[0].sensor_time_ns) * 1e-9
    assert np.abs(cloud0[ahead, 4] - span_s / 2).max() < 0.01 * span_s  # mid-turn when facing forward
    (camera,) = config.sensors.cameras
    # a Velodyne point, through our vehicle frame (the OXTS unit) into the camera, lands where the devkit puts it
    imu_velo = dict(zip(("R", "T"), (np.array(line.split(":")[1].split(), float) for line in
                                      (RAW / "calib_imu_to_velo.txt").read_text().splitlines()[1:3]), strict=True))
    t_velo_imu = np.eye(4)
    t_velo_imu[:3, :3], t_velo_imu[:3, 3] = imu_velo["R"].reshape(3, 3), imu_velo["T"]
    points = np.fromfile(RAW / "velodyne_points/data/0000000000.bin", np.float32).reshape(-1, 4)[:, :3]
    points = points[points[:, 0] > 5][::50].astype(float)
    in_vehicle = (np.linalg.inv(t_velo_imu) @ np.column_stack([points, np.ones(len(points))]).T)
    in_camera = np.linalg.inv(camera.extrinsics.matrix()) @ in_vehicle
    pixels = (camera.intrinsics.matrix() @ in_camera[:3]).T
    np.testing.assert_allclose(pixels[:, :2] / pixels[:, 2:], devkit_projection(points), atol=1e-3)
    assert camera.extrinsics.translation_m[2] + config.vehicle.reference_height_m == pytest.approx(1.65, abs=0.02)
    # the GNSS fixes and IMU samples are the OXTS records; the poses its INS solution, geo-referenced
    times, records = read_oxts(RAW)
    fixes = [r.message for r in read_log([log], topics=["gnss/fix"])]
    np.testing.assert_array_equal([f.sensor_time_ns for f in fixes], times)
    np.testing.assert_array_equal([(f.latitude_deg, f.longitude_deg, f.altitude_m) for f in fixes], records[:, :3])
    drive = start_loading_drive([str(log)], config, use_lidar=False)
    frame = LocalFrame(drive.trajectory.origin_lat_deg, drive.trajectory.origin_lon_deg,
                       drive.trajectory.origin_alt_m)
    np.testing.assert_allclose(drive.trajectory.positions, ins_positions(times, records, frame), atol=1e-6)
    yaw = Rotation.from_quat(drive.trajectory.quaternions).as_euler("ZYX")[:, 0]
    np.testing.assert_allclose(np.unwrap(yaw), np.unwrap(records[:, 5]), atol=1e-9)


def test_kitti_raw_pose_heights_put_the_road_where_the_velodyne_sees_it(tmp_path, capsys):
    """The INS poses' heights (the vertical velocity's, not the wandering GNSS altitude) against the road the
    Velodyne's first scans see ahead: its ground points lie `reference_height_m` below the trajectory at the
    trajectory point nearest them, within 12 cm in every 5 m band up to 20 m (measured -7..+8 cm; with the GNSS
    altitude -10, -27, -34 and -20 cm)."""
    log, _ = imported(tmp_path, capsys, "kitti-raw", str(RAW))
    config, _ = config_from_logs([str(log)])
    drive = start_loading_drive([str(log)], config).result()
    ground, track = drive.lidar_ground_points, drive.path
    gap, nearest = cKDTree(track.positions[:, :2]).query(ground[:, :2])
    along = track.horizontal_distance()[nearest]
    below = ground[:, 2] - (track.positions[nearest, 2] - config.vehicle.reference_height_m)
    for lo in (0.0, 5.0, 10.0, 15.0):
        band = (along >= lo) & (along < lo + 5.0) & (gap < 5.0)
        assert band.sum() > 200 and abs(np.median(below[band])) < 0.12, (lo, np.median(below[band]))


def test_kitti_raw_poses_move_as_far_as_the_unit_velocity_says():
    """The INS poses follow the unit's velocity from record to record, not its GNSS position: on 0005 the recorded
    positions cover 3.66 m in the first 1.2 s where the velocity covers 4.09 m (PnP of the camera on the Velodyne's
    depths agrees with the velocity within 8 cm there), and keyframes placed on them are too close together for
    the plane sweep (bench/RESULTS.md, 2026-12-06). Over the drive they stay within the GNSS's wander (the
    integral is 4 % longer than the recorded track: 2.1 m at most)."""
    times, records = read_oxts(RAW)
    frame = LocalFrame(*records[0, :3])
    positions = ins_positions(times, records, frame)
    t = (times - times[0]) * 1e-9
    velocity = records[:, [7, 6, 10]]  # ve, vn, vu
    step = 0.5 * (velocity[1:] + velocity[:-1]) * np.diff(t)[:, None]
    np.testing.assert_allclose(np.diff(positions, axis=0), step, atol=2e-3)
    recorded = frame.geodetic_to_enu(*records[:, :3].T)
    assert np.abs(positions - recorded).max() < 2.5


def test_kitti_raw_camera_only_map_lies_on_the_velodyne_ground(tmp_path, capsys):
    """Issue 17 item 3: 0005 mapped camera only (the plane sweep) lies within 5 cm of its own Velodyne ground for
    the first metres from the path (median signed gap 0-2 and 2-4 m: +21 / +17 cm with the poses on the recorded
    GNSS positions, -3.5 / -4.0 cm on the velocity's). ~10 s."""
    log, _ = imported(tmp_path, capsys, "kitti-raw", str(RAW))
    out = tmp_path / "map"
    assert roadlog(["reconstruct", str(log), "--out", str(out), "--no-lidar"]) == 0
    config, _ = config_from_logs([str(log)])
    drive = start_loading_drive([str(log)], config, standing=False)
    ground, track = drive.lidar_ground_points.result(), drive.path
    bev = json.loads((out / "bev.json").read_text())
    z, step, (x0, y0) = np.load(out / "bev_elevation.npy"), bev["resolution_m"], bev["origin_xy"]
    i, j = np.rint((ground[:, 1] - y0) / step).astype(int), np.rint((ground[:, 0] - x0) / step).astype(int)
    inside = (i >= 0) & (i < z.shape[0]) & (j >= 0) & (j < z.shape[1])
    gap = np.full(len(ground), np.nan)
    gap[inside] = z[i[inside], j[inside]] - ground[inside, 2]
    away = cKDTree(track.positions[:, :2]).query(ground[:, :2])[0]
    for lo, hi in ((0.0, 2.0), (2.0, 4.0)):
        band = gap[(away >= lo) & (away < hi) & np.isfinite(gap)]
        assert len(band) > 1000 and abs(np.median(band)) < 0.05, (lo, np.median(band))


def test_kitti_raw_without_its_ins_poses_is_mapped_through_pose_fusion(tmp_path, capsys):
    log, printed = imported(tmp_path, capsys, "kitti-raw", str(RAW), "--poses", "fusion")
    assert "pose" not in printed["messages"]
    config, _ = config_from_logs([str(log)])
    trajectory = start_loading_drive([str(log)], config, use_lidar=False).trajectory
    times, records = read_oxts(RAW)
    inside = (times >= trajectory.times_ns[0]) & (times <= trajectory.times_ns[-1])
    assert inside.sum() >= 90
    positions, quaternions = trajectory.interpolate(times[inside])
    # the shape of the track against the INS's own (its integrated velocity, which the fusion has from the log's
    # gnss/velocity; the recorded lat/lon wander 2 m from it over the drive, see ins_positions), and where the
    # whole track lies against it: within the fixes' stated accuracy (0.34-0.49 m)
    error = (positions - ins_positions(times, records, trajectory.local_frame)[inside])[:, :2]
    offset = error.mean(axis=0)
    shape = np.sqrt(np.mean(np.sum((error - offset) ** 2, axis=1)))
    assert shape < 0.1, shape  # measured 0.03 m (0.21 with the fixes at their stated sigma, 0.72 without velocities)
    assert np.linalg.norm(offset) < 1.0, offset  # measured 0.76 m
    heading_error = np.degrees(Rotation.from_quat(quaternions).as_euler("ZYX")[:, 0] - records[inside, 5])
    heading_rms = np.sqrt(np.mean(((heading_error + 180) % 360 - 180) ** 2))
    # measured 1.98 deg (1.45 with the fixes at their stated sigma, 4.0 without velocities), mostly a constant
    # -1.6: the OXTS's own velocity runs 1.37 deg off its x axis on average (vl / vf), which the fusion's
    # zero-sideways-velocity constraint (no wheel speeds here) takes as the car's heading
    assert heading_rms < 3.0


@pytest.mark.parametrize("damage, message", [
    (lambda d: (d / "calib_cam_to_cam.txt").unlink(), "calib_cam_to_cam.txt: calibration file missing"),
    (lambda d: (d / "oxts/data/0000000040.txt").write_text("49.0 8.4 112.8\n"), "3 fields, an OXTS record has 30"),
    (lambda d: (d / "image_02/timestamps.txt").write_text("yesterday\n"), "not a KITTI timestamp"),
    (lambda d: (d / "image_02/data/0000000090.png").write_bytes(b"GIF89a"), "0000000090.png: not a PNG file"),
])
def test_a_damaged_drive_is_a_clear_error_and_leaves_no_log(tmp_path, capsys, damage, message):
    copy = tmp_path / "drive"
    shutil.copytree(RAW, copy, ignore=shutil.ignore_patterns("velodyne_points"))
    damage(copy)
    out = tmp_path / "out.mcap"
    assert roadlog(["import", "kitti-raw", str(copy), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob("*.partial"))


@pytest.mark.parametrize("fmt, folder, extra, psnr_floor_db", [
    ("kitti-odometry", ODOMETRY, ("--no-lidar",), 18.0),  # measured 20.6 dB (bench/kitti.py)
    ("kitti-raw", RAW, (), 12.0),  # measured 13.4 dB with the Velodyne ground, 0.20 cm Elev-error
])
def test_an_imported_kitti_drive_maps_end_to_end(tmp_path, capsys, fmt, folder, extra, psnr_floor_db):
    """Imported and mapped with nothing else: no masks (maskless mode), the recorded config, the real images."""
    log, _ = imported(tmp_path, capsys, fmt, str(folder))
    out = tmp_path / "map"
    assert roadlog(["reconstruct", str(log), "--out", str(out), *extra]) == 0
    assert "have no semantic mask" in capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["semantics"].startswith("unavailable") and metrics["miou_pct"] is None
    assert metrics["psnr_db"] > psnr_floor_db, metrics["psnr_db"]
    if fmt == "kitti-raw":
        assert metrics["lidar_supervision"] and metrics["elev_error_cm"] < 1.0
        assert metrics["inputs"]["lidar_point_clouds"] == 5
    assert (out / "bev_elevation.npy").exists() and not list(out.glob("bev_semantics*"))
