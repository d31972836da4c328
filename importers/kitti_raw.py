"""`roadlog import kitti-raw DIR --out LOG.mcap`: a KITTI raw drive (colour camera `image_02`, OXTS GPS/IMU records,
the calibration files) as a roadlog log that `roadlog reconstruct LOG` maps with nothing else.

The OXTS unit's records become GNSS fixes (its position, with its stated accuracy as the covariance) and IMU samples
(body-frame specific force and angular rate), so pose fusion runs on them like on any car's GNSS/IMU. The vehicle
frame is the OXTS frame (x forward, y left, z up), `--reference-height-m` (KITTI's setup: 0.93 m) above the road; the
camera's extrinsics follow from calib_imu_to_velo, calib_velo_to_cam and the rectification (P_rect_02, R_rect_00).
The Velodyne scans (velodyne_points/, when present) become point clouds of a `point-cloud` Lidar mounted as
calib_imu_to_velo says.
Frames carry their PNG bytes unchanged; every stamp is KITTI's UTC time, on one clock, with time anchors saying so.

`--poses oxts` (the default) also writes the unit's own INS solution (its position and roll/pitch/yaw, KITTI's
reference poses; the positions from its velocity, as its GNSS position wanders: ins_positions) as the `pose`
topic, which `reconstruct` then uses instead of fusing; `--poses fusion` leaves it out. Measured on
2011_09_26_drive_0005: our fusion of the 10 Hz OXTS fixes and IMU samples (no wheel speeds) is 0.13 m RMS from the
INS positions but 4.0 deg RMS (8.2 deg at worst) from its heading, too far for a map.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.log_format.metadata_records import POSE_ENU_ORIGIN_KEY
from daemon.spine.config import POINT_CLOUD_LIDAR, reports_config_errors
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import GnssFix, GnssVelocity, ImuSample, PointCloud, TimeAnchor, VehiclePose
from daemon.spine.point_cloud_codec import pack_points
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU, LIDAR_POINTS, POSE, TIME_ANCHOR
from drivers.gnss.receiver_epochs import covariance_diagonal
from importers.imported_log import ImportSummary, imported_log
from importers.kitti_files import (
    DatasetError,
    calibration_matrix,
    extrinsics,
    imported_car_config,
    numbered_files,
    png_file_size,
    read_calibration,
    read_timestamps,
    recorded_camera,
    rigid,
    write_png_frames,
)

CAMERA = "image_02"
OXTS_FIELDS = ("lat lon alt roll pitch yaw vn ve vf vl vu ax ay az af al au wx wy wz wf wl wu pos_accuracy "
               "vel_accuracy navstat numsats posmode velmode orimode").split()
_FIELD = {name: i for i, name in enumerate(OXTS_FIELDS)}
GNSS_TIME_CONSTANT_S = 20.0  # the poses' positions: the velocity's within it, the GNSS position's beyond


def velodyne_scans(folder: Path) -> list[PointCloud]:
    """velodyne_points/: each .bin scan (float32 x, y, z, reflectance, Lidar frame) as a point cloud starting at its
    timestamps_start time. KITTI gives no time per point: the HDL-64E turns clockwise seen from above from the back
    (timestamps_start) through the front (timestamps.txt, mid-scan) to the back again (timestamps_end), so a point's
    time is the fraction of that turn its azimuth has swept."""
    base = folder / "velodyne_points"
    if not base.is_dir():
        return []
    files = numbered_files(base / "data", ".bin")
    starts, ends = read_timestamps(base / "timestamps_start.txt"), read_timestamps(base / "timestamps_end.txt")
    if not len(files) <= min(len(starts), len(ends)):
        raise DatasetError(f"{base}: {len(files)} scans for {len(starts)} start and {len(ends)} end times")
    clouds = []
    for path in files:
        raw = np.fromfile(path, np.float32)
        if raw.size % 4:
            raise DatasetError(f"{path}: {raw.size * 4} bytes, not whole (x, y, z, reflectance) float32 points")
        points = raw.reshape(-1, 4)
        k = int(path.stem)
        swept = (np.pi - np.arctan2(points[:, 1], points[:, 0])) / (2 * np.pi)  # 0 at the back, 0.5 ahead
        clouds.append(PointCloud(seq=k, sensor_time_ns=int(starts[k]), host_mono_ns=int(ends[k]),
                                 data=pack_points(points[:, :3], points[:, 3], swept * (ends[k] - starts[k]) * 1e-9)))
    return clouds


def imu_to_velodyne(folder: Path) -> np.ndarray:
    path = folder / "calib_imu_to_velo.txt"
    values = read_calibration(path)
    return rigid(calibration_matrix(values, "R", (3, 3), path), calibration_matrix(values, "T", (3, 1), path)[:, 0])


def imu_to_camera(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(T_cam_imu of the rectified colour camera 2, its 3x3 K) from the three calibration files."""
    cam_path, velo_path = (folder / f"calib_{n}.txt" for n in ("cam_to_cam", "velo_to_cam"))
    cam, velo = read_calibration(cam_path), read_calibration(velo_path)
    p_rect = calibration_matrix(cam, "P_rect_02", (3, 4), cam_path)
    r_rect = calibration_matrix(cam, "R_rect_00", (3, 3), cam_path)
    t_cam0_velo = rigid(calibration_matrix(velo, "R", (3, 3), velo_path), calibration_matrix(velo, "T", (3, 1),
                                                                                            velo_path)[:, 0])
    k = p_rect[:, :3]
    t_cam2_cam0rect = rigid(np.eye(3), np.linalg.solve(k, p_rect[:, 3]))  # camera 2's baseline from P_rect_02
    return t_cam2_cam0rect @ rigid(r_rect, np.zeros(3)) @ t_cam0_velo @ imu_to_velodyne(folder), k


def read_oxts(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(UTC ns, (N, 30) records) of oxts/; a record with the wrong number of fields is a DatasetError."""
    times = read_timestamps(folder / "oxts" / "timestamps.txt")
    files = numbered_files(folder / "oxts" / "data", ".txt")
    if len(files) != len(times):
        raise DatasetError(f"{folder / 'oxts'}: {len(files)} records for {len(times)} timestamps")
    records = []
    for path in files:
        values = path.read_text().split()
        if len(values) != len(OXTS_FIELDS):
            raise DatasetError(f"{path}: {len(values)} fields, an OXTS record has {len(OXTS_FIELDS)}")
        records.append([float(v) for v in values])
    return times, np.array(records)


def oxts_messages(times: np.ndarray, records: np.ndarray
                  ) -> tuple[list[GnssFix], list[GnssVelocity], list[ImuSample]]:
    """Each OXTS record as a GNSS fix (position accuracy as a diagonal covariance), a GNSS velocity (ve, vn, vu; the
    unit's velocity accuracy, given for north/east, taken for up too) and an IMU sample (x, y, z: the vehicle's
    front, left and top; the af/al/au and wf/wl/wu columns are the levelled ones, not used)."""
    f = _FIELD
    fixes, velocities, samples = [], [], []
    for i, (t, r) in enumerate(zip(times.tolist(), records, strict=True)):
        sigma = max(float(r[f["pos_accuracy"]]), 0.01)
        fixes.append(GnssFix(seq=i, sensor_time_ns=t, host_mono_ns=t, latitude_deg=float(r[f["lat"]]),
                             longitude_deg=float(r[f["lon"]]), altitude_m=float(r[f["alt"]]),
                             position_covariance=covariance_diagonal(sigma, sigma, sigma),
                             covariance_type=2))
        v_sigma = max(float(r[f["vel_accuracy"]]), 0.01)
        velocities.append(GnssVelocity(seq=i, sensor_time_ns=t, host_mono_ns=t,
                                       velocity_enu_mps=tuple(float(r[f[k]]) for k in ("ve", "vn", "vu")),
                                       velocity_covariance=covariance_diagonal(v_sigma, v_sigma, v_sigma),
                                       covariance_type=2))
        samples.append(ImuSample(seq=i, sensor_time_ns=t, host_mono_ns=t,
                                 accel_mps2=tuple(float(r[f[k]]) for k in ("ax", "ay", "az")),
                                 gyro_rps=tuple(float(r[f[k]]) for k in ("wx", "wy", "wz"))))
    return fixes, velocities, samples


def ins_positions(times: np.ndarray, records: np.ndarray, frame: LocalFrame) -> np.ndarray:
    """(N, 3) ENU positions (m) of the poses: the unit's velocity (`ve`, `vn`, `vu`) integrated (trapezoids) for
    what changes within GNSS_TIME_CONSTANT_S, its GNSS position (lat, lon, alt) for what changes slower (a
    complementary filter: the position less the integral, smoothed forward and backward by a first-order
    low-pass, added back).
    On 2011_09_26_drive_0005 the recorded altitude rises 0.42 m over the first 3 s and falls back while `vu`
    and the pitch both say the car descends steadily (-0.3 m over 33 m); and the recorded positions cover 32.6 m
    where the velocity covers 34.0 m, 0.43 m short in the first 1.2 s alone (the camera placed by the Velodyne's
    depths, PnP, is 24 cm ahead of them 1-2.5 s on, 8-17 cm behind the velocity's). Keyframes placed on those
    positions are too close together, and a surface the plane sweep triangulates from them too near the
    cameras: the camera-only map lay 21 cm above the Velodyne ground near the path (-4 cm on these)."""
    f = _FIELD
    t = (times - times[0]) * 1e-9
    velocity = records[:, [f["ve"], f["vn"], f["vu"]]]
    moved = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (velocity[1:] + velocity[:-1]) * np.diff(t)[:, None],
                                                        axis=0)])
    offset = frame.geodetic_to_enu(records[:, f["lat"]], records[:, f["lon"]], records[:, f["alt"]]) - moved
    for order in (slice(None), slice(None, None, -1)):  # zero phase: forward, then backward
        smoothed, previous = offset[order].copy(), None
        for i, dt in enumerate(np.abs(np.diff(t[order], prepend=t[order][0]))):
            if previous is not None:
                smoothed[i] = previous + (1.0 - np.exp(-dt / GNSS_TIME_CONSTANT_S)) * (smoothed[i] - previous)
            previous = smoothed[i]
        offset[order] = smoothed
    return moved + offset


def oxts_poses(times: np.ndarray, records: np.ndarray) -> list[VehiclePose]:
    """The OXTS unit's INS solution as vehicle poses in the ENU frame at its first position (KITTI's convention:
    R = Rz(yaw) Ry(pitch) Rx(roll), yaw 0 = east, pitch positive = front down, roll positive = left side up),
    at the positions of ins_positions (its GNSS position wanders by decimetres within seconds)."""
    f = _FIELD
    frame = LocalFrame(float(records[0, f["lat"]]), float(records[0, f["lon"]]), float(records[0, f["alt"]]))
    positions = ins_positions(times, records, frame)
    angles = records[:, [f["yaw"], f["pitch"], f["roll"]]]
    quaternions = Rotation.from_euler("ZYX", angles).as_quat()
    return [VehiclePose(seq=i, sensor_time_ns=t, host_mono_ns=t, frame_id="enu",
                        position_m=tuple(float(v) for v in p), orientation_xyzw=tuple(float(v) for v in q))
            for i, (t, p, q) in enumerate(zip(times.tolist(), positions, quaternions, strict=True))]


def import_raw(folder: Path, out: Path, *, reference_height_m: float = 0.93, poses: str = "oxts") -> ImportSummary:
    started = time.perf_counter()
    t_cam_imu, k = imu_to_camera(folder)
    images = numbered_files(folder / CAMERA / "data", ".png")
    frame_times = read_timestamps(folder / CAMERA / "timestamps.txt")
    if len(frame_times) != len(images):
        raise DatasetError(f"{folder / CAMERA}: {len(images)} images for {len(frame_times)} timestamps")
    oxts_times, records = read_oxts(folder)
    fixes, velocities, samples = oxts_messages(oxts_times, records)
    width, height = png_file_size(images[0])
    rate_hz = float((len(frame_times) - 1) / ((frame_times[-1] - frame_times[0]) * 1e-9))
    camera = recorded_camera(CAMERA, width, height, k, np.linalg.inv(t_cam_imu), round(rate_hz, 3), "png")
    oxts_rate = round(float((len(oxts_times) - 1) / ((oxts_times[-1] - oxts_times[0]) * 1e-9)), 3)
    gnss = {"port": "", "rate_hz": oxts_rate, "imu_rate_hz": oxts_rate}  # the OXTS unit: position at the IMU
    clouds = velodyne_scans(folder)
    lidar = {"lidar": {"model": POINT_CLOUD_LIDAR, "extrinsics": extrinsics(np.linalg.inv(imu_to_velodyne(folder)))}}
    config = imported_car_config("kitti-raw", [camera], reference_height_m, folder, gnss=gnss,
                                 **(lidar if clouds else {}))
    metadata = {"source": f"KITTI raw {folder.resolve()}",
                "import": json.dumps({"reference_height_m": reference_height_m, "poses": poses})}
    if poses == "oxts":
        metadata[POSE_ENU_ORIGIN_KEY] = json.dumps([float(v) for v in records[0, :3]])  # oxts_poses' ENU frame
    with imported_log(out, config, metadata) as writer:
        start, end = int(min(frame_times[0], oxts_times[0])), int(max(frame_times[-1], oxts_times[-1]))
        for i, t in enumerate(range(start, end + 1_000_000_000, 1_000_000_000)):
            writer.write(TIME_ANCHOR, TimeAnchor(seq=i, sensor_time_ns=t, host_mono_ns=t, utc_ns=t))
        for fix, velocity, sample in zip(fixes, velocities, samples, strict=True):
            writer.write(GNSS_FIX, fix)
            writer.write(GNSS_VELOCITY, velocity)
            writer.write(IMU, sample)
        for pose in oxts_poses(oxts_times, records) if poses == "oxts" else ():
            writer.write(POSE, pose)
        for cloud in clouds:
            writer.write(LIDAR_POINTS, cloud)
        write_png_frames(writer, CAMERA, images, frame_times.tolist(), (width, height))
        counts = dict(writer.counts)
    return ImportSummary(out, counts, float(frame_times[-1] - frame_times[0]) / 1e9, time.perf_counter() - started)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", type=Path, help="the drive folder (image_02/, oxts/, calib_*.txt)")
    parser.add_argument("--out", required=True, type=Path, help="the MCAP log to write")
    parser.add_argument("--reference-height-m", type=float, default=0.93, help="the OXTS unit above the road (m)")
    parser.add_argument("--poses", choices=("oxts", "fusion"), default="oxts",
                        help="oxts: also write the unit's INS poses as the pose topic; fusion: leave them to fusion")


@reports_config_errors
def run(args: argparse.Namespace) -> int:
    print(import_raw(args.folder, args.out, reference_height_m=args.reference_height_m, poses=args.poses).as_json())
    return 0
