"""From drive logs to the reconstruction's inputs: clock alignment, pose fusion, keyframes, Lidar ground.

Every sensor has its own clock: each topic's stamps are put on the host monotonic clock
(mapping.localization.sensor_time). The trajectory comes from the log's `pose` topic when it has one, else
from fusing its GNSS, IMU and wheel speeds (mapping.localization.pose_fusion). Camera frames become keyframes
every `keyframe_spacing_m` of travel (per camera); their poses are interpolated at the frame time.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from daemon.log_format.metadata_records import METADATA_NAME, POSE_ENU_ORIGIN_KEY
from daemon.log_format.reader import ReadReport, read_log, read_metadata, summary_message_count
from daemon.spine.config import CarConfig
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import (
    RAW_FORMAT_CHANNELS,
    CameraFrame,
    GnssFix,
    GnssVelocity,
    ImuSample,
    LidarPacket,
    PointCloud,
    SemanticMask,
    TimeAnchor,
    VehiclePose,
    WheelSpeeds,
)
from daemon.spine.topics import (
    FUSION_TOPICS,
    GNSS_FIX,
    GNSS_VELOCITY,
    IMU,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    LIDAR_VIEW,
    POSE,
    TIME_ANCHOR,
    WHEEL_SPEEDS,
    camera_topic,
    mask_topic,
)
from mapping.inputs.lidar_ground import GroundFilter, configured_decoding, lidar_scans, scans_ground
from mapping.inputs.segmentation import OnnxSegmenter
from mapping.localization import pose_fusion
from mapping.localization.keyframe_spacing import spaced_preferring
from mapping.localization.pose_noise import PoseNoise, perturbed
from mapping.localization.sensor_time import ClockMap, fit_clock, span_clock
from mapping.localization.trajectory import HorizontalTrack, Trajectory
from mapping.method.scene_data import CameraModel, Keyframe, StandingPoints


@dataclass
class DriveInputs:
    cameras: dict[str, CameraModel]
    keyframes: list[Keyframe]
    trajectory: Trajectory  # 6-DoF vehicle reference frame in ENU, host monotonic ns
    lidar_ground_points: np.ndarray | None
    clocks: dict[str, ClockMap]  # per topic: its sensor stamps -> host monotonic
    counts: dict[str, int] = field(default_factory=dict)
    report: ReadReport | None = None
    lidar_standing: StandingPoints | None = None  # what stands on the road, for the keyframes without masks
    lidar_ground_times: np.ndarray | None = None  # (N,) each ground point's firing time, s from the track's start
    gnss_std_m: tuple[float, float] | None = None  # gnss_std_m(): its fixes' reported accuracy; None: no fixes
    lidar_ground_contrast: np.ndarray | None = None  # (N,) each ground point's intensity contrast
    # (mapping.inputs.lidar_ground.intensity_contrast; NaN: the Lidar gave no intensity)

    @property
    def path(self) -> HorizontalTrack:
        return self.trajectory.horizontal_track()

    @property
    def drive_s(self) -> float:
        return float(self.trajectory.times_ns[-1] - self.trajectory.times_ns[0]) / 1e9


@dataclass
class LoadingDrive:
    """A drive whose trajectory is ready while its Lidar ground is extracted, then its keyframe images decoded,
    in a background thread (numpy and OpenCV release the GIL): the reconstruction builds its mesh meanwhile
    and waits for each input where it first needs it."""

    cameras: dict[str, CameraModel]
    keyframes: Future[list[Keyframe]]
    trajectory: Trajectory
    lidar_ground_points: Future[np.ndarray | None]
    clocks: dict[str, ClockMap]
    counts: dict[str, int]
    report: ReadReport
    lidar_standing: Future[StandingPoints | None]  # None: no Lidar, or every keyframe has a mask
    lidar_ground_times: Future[np.ndarray | None]  # (N,) each ground point's firing time, s from the track's start
    gnss_std_m: tuple[float, float] | None = None
    lidar_ground_contrast: Future[np.ndarray | None] | None = None  # (N,) each ground point's intensity contrast

    @property
    def path(self) -> HorizontalTrack:
        return self.trajectory.horizontal_track()

    def result(self) -> DriveInputs:
        """The finished inputs (waits for the background work; its errors are raised here)."""
        keyframes, ground = self.keyframes.result(), self.lidar_ground_points.result()
        counts = dict(self.counts, keyframes=len(keyframes))
        if ground is not None:
            counts["lidar_ground_points"] = len(ground)
        return DriveInputs(self.cameras, keyframes, self.trajectory, ground, self.clocks, counts, self.report,
                           self.lidar_standing.result(), self.lidar_ground_times.result(), self.gnss_std_m,
                           None if self.lidar_ground_contrast is None else self.lidar_ground_contrast.result())


def camera_models(config: CarConfig) -> dict[str, CameraModel]:
    return {c.name: CameraModel(c.name, c.intrinsics.matrix(), tuple(c.distortion), c.width, c.height,
                                c.extrinsics.rotation_matrix()) for c in config.sensors.cameras}


def decode_image(frame: CameraFrame) -> np.ndarray:
    """RGB uint8 pixels of a camera frame (JPEG/PNG or raw)."""
    if frame.format in RAW_FORMAT_CHANNELS:
        channels = RAW_FORMAT_CHANNELS[frame.format]
        img = np.frombuffer(bytes(frame.data), np.uint8).reshape(frame.height, frame.width, channels)
        if frame.format == "bgr8":
            img = img[..., ::-1]
        return np.repeat(img, 3, axis=2) if channels == 1 else np.ascontiguousarray(img)
    img = cv2.imdecode(np.frombuffer(bytes(frame.data), np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"cannot decode {frame.format} frame {frame.seq} of {frame.camera}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_mask(mask: SemanticMask) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(bytes(mask.data), np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot decode mask {mask.seq} of {mask.camera}")
    return img


def gnss_std_m(gnss: list[GnssFix]) -> tuple[float, float] | None:
    """(horizontal, vertical) 1-sigma the receiver reported for its fixes, the median over the drive (horizontal:
    the RMS of east and north); None without fixes or without covariances (type unknown, or not positive)."""
    cov = np.array([np.reshape(m.position_covariance, (3, 3)) for m in gnss
                    if m.covariance_type != 0 and len(m.position_covariance) == 9])
    if not len(cov):
        return None
    diag = np.diagonal(cov, axis1=1, axis2=2)
    ok = np.all(np.isfinite(diag) & (diag > 0), axis=1)
    if not ok.any():
        return None
    return (float(np.median(np.sqrt((diag[ok, 0] + diag[ok, 1]) / 2))), float(np.median(np.sqrt(diag[ok, 2]))))


def _by_sensor_time(messages: list) -> list:
    """Messages sorted by their sensor time, repeated stamps dropped (arrival order may differ)."""
    out, last = [], None
    for m in sorted(messages, key=lambda m: m.sensor_time_ns):
        if m.sensor_time_ns != last:
            out.append(m)
            last = m.sensor_time_ns
    return out


def fix_velocities(gnss: list[GnssFix], velocities: list[GnssVelocity]) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 3) ENU velocity (m/s) and (N, 3, 3) covariance of each fix, from the receiver's velocity of the same epoch
    (equal sensor times to the millisecond); NaN rows where it sent none or gave no covariance. None without any."""
    by_epoch = {round(v.sensor_time_ns / 1e6): v for v in velocities
                if v.covariance_type != 0 and len(v.velocity_covariance) == 9}
    velocity = np.full((len(gnss), 3), np.nan)
    cov = np.full((len(gnss), 3, 3), np.nan)
    for i, fix in enumerate(gnss):
        v = by_epoch.get(round(fix.sensor_time_ns / 1e6))
        if v is not None:
            velocity[i] = v.velocity_enu_mps
            cov[i] = np.reshape(v.velocity_covariance, (3, 3))
    usable = np.all(np.isfinite(velocity), axis=1) & np.all(np.diagonal(cov, axis1=1, axis2=2) > 0, axis=1)
    velocity[~usable] = np.nan
    return (velocity, cov) if usable.any() else None


def fuse_log_trajectory(gnss: list[GnssFix], imu: list[ImuSample], wheels: list[WheelSpeeds], config: CarConfig,
                        origin: LocalFrame | None, clocks: dict[str, ClockMap],
                        velocities: list[GnssVelocity] = ()) -> Trajectory:
    """The vehicle trajectory from the log's GNSS (its fixes and, where the receiver sends it, its velocity), IMU and
    (when it has them) wheel speeds (host clock)."""
    if not gnss or not imu:
        raise ValueError(f"pose fusion needs GNSS and IMU, wheel speeds where the car has them (got {len(gnss)} "
                         f"fixes, {len(imu)} IMU samples, {len(wheels)} wheel speeds) or a `pose` topic in the log")
    g = config.sensors.gnss
    gnss, imu, wheels = _by_sensor_time(gnss), _by_sensor_time(imu), _by_sensor_time(wheels)
    velocity = fix_velocities(gnss, velocities)
    fixes = pose_fusion.GnssFixes(
        times_ns=clocks[GNSS_FIX].to_host([m.sensor_time_ns for m in gnss]),
        lat_deg=np.array([m.latitude_deg for m in gnss]),
        lon_deg=np.array([m.longitude_deg for m in gnss]),
        alt_m=np.array([m.altitude_m for m in gnss]),
        position_cov_enu=np.array([np.reshape(m.position_covariance, (3, 3)) for m in gnss]),
        velocity_enu=None if velocity is None else velocity[0],
        velocity_cov_enu=None if velocity is None else velocity[1],
    )
    samples = pose_fusion.ImuSamples(
        times_ns=clocks[IMU].to_host([m.sensor_time_ns for m in imu]),
        accel=np.array([m.accel_mps2 for m in imu]),
        gyro=np.array([m.gyro_rps for m in imu]),
    )
    yaw = np.array([m.yaw_rate_rps for m in wheels])
    speeds = pose_fusion.WheelSpeeds(
        times_ns=clocks[WHEEL_SPEEDS].to_host([m.sensor_time_ns for m in wheels]),
        speeds=np.array([[m.front_left_mps, m.front_right_mps, m.rear_left_mps, m.rear_right_mps] for m in wheels]),
        yaw_rate=None if np.all(np.isnan(yaw)) else yaw,
    ) if wheels else None
    mounting = pose_fusion.VehicleMounting(
        gnss_lever_arm=np.array(g.antenna_lever_arm_m, float),
        imu_lever_arm=np.array(g.imu_extrinsics.translation_m, float),
        rear_axle_lever_arm=np.array(config.vehicle.rear_axle_m, float),
        wheel_base_m=config.vehicle.wheel_base_m,
        imu_to_vehicle=g.imu_extrinsics.rotation_matrix(),
    )
    settings = pose_fusion.FusionSettings(accel_bias_sigma=g.imu_accel_bias_sigma_mps2)
    return pose_fusion.fuse_trajectory(fixes, samples, speeds, mounting, origin=origin, settings=settings).trajectory


def fuse_bus_trajectory(held: dict[str, list], config: CarConfig, origin: LocalFrame) -> Trajectory:
    """The trajectory from the GNSS fixes, IMU samples, wheel speeds and time anchors a live consumer holds as they
    came off the bus (by topic; its last seconds or minutes: each sensor's clock by `span_clock`)."""
    anchors = [(m.host_mono_ns, m.utc_ns) for m in held[TIME_ANCHOR]]
    clocks = {t: span_clock([m.sensor_time_ns for m in held[t]], [m.host_mono_ns for m in held[t]], anchors)
              for t in (GNSS_FIX, IMU, WHEEL_SPEEDS)}
    return fuse_log_trajectory(held[GNSS_FIX], held[IMU], held[WHEEL_SPEEDS], config, origin, clocks,
                               held.get(GNSS_VELOCITY, []))


def _pose_trajectory(poses: list[VehiclePose], clock: ClockMap, origin: LocalFrame | None) -> Trajectory:
    o = origin or LocalFrame(0.0, 0.0, 0.0)
    return Trajectory(
        times_ns=clock.to_host([p.sensor_time_ns for p in poses]),
        positions=np.array([p.position_m for p in poses], float),
        quaternions=np.array([p.orientation_xyzw for p in poses], float),
        origin_lat_deg=o.lat_deg, origin_lon_deg=o.lon_deg, origin_alt_m=o.alt_m,
    )


def recorded_pose_origin(path: str | Path) -> LocalFrame | None:
    """The geo-reference of a log's `pose` topic, where its writer recorded one (metadata_records)."""
    value = read_metadata(path).get(METADATA_NAME, {}).get(POSE_ENU_ORIGIN_KEY)
    return LocalFrame(*(float(v) for v in json.loads(value))) if value else None


def camera_pose(trajectory: Trajectory, t_ns: int, T_vehicle_camera: np.ndarray) -> np.ndarray:
    """4x4 T_world_camera at one time."""
    pos, quat = trajectory.interpolate(np.array([t_ns], np.int64))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quat[0]).as_matrix()
    T[:3, 3] = pos[0]
    return T @ T_vehicle_camera


def load_drive(paths: list[str | Path], config: CarConfig, config_path: str | Path | None = None,
               **options) -> DriveInputs:
    """Everything the reconstruction needs from the given log segments (options: start_loading_drive's)."""
    return start_loading_drive(paths, config, config_path, **options).result()


def start_loading_drive(paths: list[str | Path], config: CarConfig, config_path: str | Path | None = None, *,
                        origin: LocalFrame | None = None, use_lidar: bool = True,
                        standing: bool | None = None, progress: bool = False,
                        pose_noise: PoseNoise | None = None,
                        trajectory_correction: Callable[[Trajectory], Trajectory] | None = None) -> LoadingDrive:
    """Read the log segments and fuse the trajectory; start extracting the Lidar ground (every
    `mapper.inputs.lidar_every_n_scans`-th scan) and decoding the keyframes (every
    `mapper.inputs.keyframe_spacing_m`) in the background. The Lidar's standing points come too when a keyframe
    has no mask and `mapper.maskless.lidar_occlusion` is on (`standing` True / False: always / never). `progress`:
    a bar with its ETA on stderr for each of the three (the messages read, the scans, the keyframes decoded).
    `pose_noise`: an error injected into the trajectory before anything is placed with it (benches:
    mapping.localization.pose_noise). `trajectory_correction`: applied to the trajectory (after the noise) before
    anything is placed with it (the pose refinement's Lidar pre-pass, mapping.offline.reconstruct_command)."""
    report = ReadReport()
    segmenter = segmenter_for(config, config_path)  # a bad model fails here, before the log is read
    cams = [c.name for c in config.sensors.cameras]
    frames: dict[str, list[CameraFrame]] = defaultdict(list)
    masks: dict[str, dict[int, SemanticMask]] = defaultdict(dict)
    gnss, velocities, imu, wheels, poses, packets, clouds, view_clouds = [], [], [], [], [], [], [], []
    wanted = {camera_topic(c) for c in cams} | ({mask_topic(c) for c in cams} if segmenter is None else set())
    wanted |= {*FUSION_TOPICS, POSE, TIME_ANCHOR}
    anchors: list[tuple[int, int]] = []
    if use_lidar and config.sensors.lidar is not None:
        # a log of a point-cloud Lidar (or an imported one) has points; one without either, its viewing clouds
        wanted |= {LIDAR_PACKETS, LIDAR_POINTS, LIDAR_VIEW}
    host_sensor: dict[str, list[tuple[int, int]]] = defaultdict(list)
    reading = tqdm(read_log(paths, topics=wanted, report=report), desc="read logs", unit="msg", mininterval=0.5,
                   total=summary_message_count(paths, wanted) if progress else None, disable=not progress)
    for rec in reading:
        m = rec.message
        if isinstance(m, TimeAnchor):
            anchors.append((m.host_mono_ns, m.utc_ns))
            continue
        host_sensor[rec.topic].append((m.host_mono_ns, m.sensor_time_ns))
        if isinstance(m, CameraFrame):
            frames[m.camera].append(m)
        elif isinstance(m, SemanticMask):
            masks[m.camera][m.sensor_time_ns] = m
        elif isinstance(m, GnssFix):
            gnss.append(m)
        elif isinstance(m, GnssVelocity):
            velocities.append(m)
        elif isinstance(m, ImuSample):
            imu.append(m)
        elif isinstance(m, WheelSpeeds):
            wheels.append(m)
        elif isinstance(m, VehiclePose):
            poses.append(m)
        elif isinstance(m, LidarPacket):
            packets.append(m)
        elif isinstance(m, PointCloud):
            (view_clouds if rec.topic == LIDAR_VIEW else clouds).append(m)
    clocks = {t: fit_clock([s for _, s in v], [h for h, _ in v], anchors) for t, v in host_sensor.items()}
    if poses:
        trajectory = _pose_trajectory(poses, clocks[POSE], origin or recorded_pose_origin(paths[0]))
    else:
        trajectory = fuse_log_trajectory(gnss, imu, wheels, config, origin, clocks, velocities)
    if pose_noise is not None:
        trajectory = perturbed(trajectory, pose_noise)
    if trajectory_correction is not None:
        trajectory = trajectory_correction(trajectory)
    chosen, counts = _keyframe_messages(config, frames, masks if segmenter is None else None, clocks, trajectory,
                                        config.mapper.inputs.keyframe_spacing_m)
    # one background thread, the Lidar first: the reconstruction needs it first (its elevation fit), and the
    # decoding then runs beside that single-threaded fit. The pool lets its thread finish after shutdown.
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="load-drive")
    lidar = config.sensors.lidar

    # a bad metadata or calibration file fails here, before the background work
    scans = lidar_scans(packets, clouds, lambda: configured_decoding(lidar, config_path or "."),
                        config.mapper.inputs.lidar_every_n_scans, view_clouds) if lidar else None
    ground, ground_times, standing_points, contrast = Future(), Future(), Future(), Future()
    if scans is not None:
        occlusion = (counts["keyframes_without_mask"] > 0 and config.mapper.maskless.lidar_occlusion
                     if standing is None else standing)
        points = pool.submit(scans_ground, scans, clocks[scans.topic], config, trajectory,
                             GroundFilter(corridor_half_width_m=config.mapper.mesh.corridor_half_width_m),
                             int(trajectory.times_ns[0]) if occlusion else None, progress)
        points.add_done_callback(lambda done: _split(done, ground, ground_times, standing_points, contrast))
        counts.update(scans.counts)
    else:
        ground.set_result(None)
        ground_times.set_result(None)
        standing_points.set_result(None)
        contrast.set_result(None)
    keyframes = pool.submit(_decode_keyframes, chosen, segmenter, progress)
    pool.shutdown(wait=False)
    return LoadingDrive(camera_models(config), keyframes, trajectory, ground, clocks, counts, report,
                        standing_points, ground_times, gnss_std_m(gnss), contrast)


def _split(done: Future, *parts: Future) -> None:
    """The results of a finished future (a tuple) into one future each (its error into all)."""
    if done.exception() is not None:
        for part in parts:
            part.set_exception(done.exception())
    else:
        for part, value in zip(parts, done.result(), strict=True):
            part.set_result(value)


@dataclass(frozen=True)
class _KeyframeMessages:
    """A camera frame chosen as keyframe, its mask and pose, not decoded yet."""

    camera: str
    timestamp: float  # seconds from the trajectory start
    T_world_camera: np.ndarray
    frame: CameraFrame
    mask: SemanticMask | None  # None: the segmentation model labels the frame, or it has no mask (no semantics)


def spaced_camera_frames(frames: list[tuple[CameraFrame, int]], masks: dict[int, SemanticMask] | None,
                         trajectory: Trajectory, spacing_m: float
                         ) -> list[tuple[CameraFrame, int, SemanticMask | None]]:
    """One camera's keyframes among `frames` ((frame, host time), in time order, inside `trajectory`): one every
    `spacing_m` along the trajectory (3-D), each with its mask (by sensor time) or None. A frame without a mask
    is passed over for one with a mask within `spacing_m` after it, and kept (without semantics) when there is
    none (keyframe_spacing.spaced_preferring). `masks` None: a segmentation model labels every frame."""
    if not frames:
        return []
    distance = trajectory.distance_3d_at(np.array([t for _, t in frames], np.int64))
    at = {id(f): float(d) for (f, _), d in zip(frames, distance, strict=True)}

    def has_mask(frame_time: tuple[CameraFrame, int]) -> bool:
        return masks is None or frame_time[0].sensor_time_ns in masks

    kept = spaced_preferring(frames, lambda ft: at[id(ft[0])], spacing_m, has_mask)
    return [(f, t, masks.get(f.sensor_time_ns) if masks is not None else None) for f, t in kept]


def _keyframe_messages(config: CarConfig, frames: dict[str, list[CameraFrame]],
                       masks: dict[str, dict[int, SemanticMask]] | None, clocks: dict[str, ClockMap],
                       trajectory: Trajectory, spacing_m: float) -> tuple[list[_KeyframeMessages], dict[str, int]]:
    """Per camera, a frame every `spacing_m` of travel (spaced_camera_frames), with its mask unless `masks` is
    None (a model labels the frames); the counts of the frames, of those passed over and of those without a
    mask (`frames_without_mask`: every frame of the log that has none, `keyframes_without_mask`: the keyframes
    among them)."""
    chosen, counts = [], {"frames": 0, "frames_without_mask": 0, "frames_outside_trajectory": 0,
                          "keyframes_without_mask": 0}
    t0 = trajectory.times_ns[0]
    for cam in config.sensors.cameras:
        T_vc = cam.extrinsics.matrix()
        cam_masks = masks.get(cam.name, {}) if masks is not None else None
        inside = []  # (frame, host time)
        for f in frames.get(cam.name, []):
            counts["frames"] += 1
            if cam_masks is not None and f.sensor_time_ns not in cam_masks:
                counts["frames_without_mask"] += 1
            t = int(clocks[camera_topic(cam.name)].to_host([f.sensor_time_ns])[0])
            if not trajectory.times_ns[0] <= t <= trajectory.times_ns[-1]:
                counts["frames_outside_trajectory"] += 1
                continue
            inside.append((f, t))
        for f, t, mask in spaced_camera_frames(inside, cam_masks, trajectory, spacing_m):
            counts["keyframes_without_mask"] += cam_masks is not None and mask is None
            chosen.append(_KeyframeMessages(cam.name, (t - t0) / 1e9, camera_pose(trajectory, t, T_vc), f, mask))
    chosen.sort(key=lambda k: k.timestamp)
    return chosen, counts


def missing_masks_warning(frames: int, without_mask: int) -> str | None:
    """The warning for a drive of `frames` camera frames of which `without_mask` have no semantic mask and no
    segmentation model labels them (None when every frame is labelled)."""
    if without_mask == 0:
        return None
    if without_mask >= frames:
        what = "the map has colour and elevation only (semantics unavailable)"
    else:
        what = "semantics come from the frames with a mask only, colour and elevation from all"
    return (f"{without_mask} of {frames} camera frames have no semantic mask and no segmentation model is "
            f"configured (mapper.segmentation.provider: log): {what}")


def keyframe_semantics(image: np.ndarray, mask: SemanticMask | None,
                       segmenter: OnnxSegmenter | None) -> np.ndarray | None:
    """A keyframe's class ids: the model's labels of its image if a segmenter is given, else its recorded mask
    (None without one: the keyframe gives colour and elevation only)."""
    if segmenter is not None:
        return segmenter.labels(image)
    return decode_mask(mask) if mask is not None else None


def check_config(car: CarConfig, config_path: str | Path) -> None:
    """What the mapper (live worker or reconstruct) needs of the config before it starts (also run by `roadlog
    check-config`): the segmentation model loads, the Lidar metadata or calibration reads and fits the model (a
    point-cloud Lidar has none), the torch device is there (mapper.device: cuda needs a CUDA GPU)."""
    from mapping.method.compute_device import resolve_device  # torch, only for the check

    resolve_device(car.mapper.device, f"{config_path}: mapper.device")
    segmenter_for(car, config_path)
    if car.sensors.lidar is not None:
        configured_decoding(car.sensors.lidar, config_path)


def segmenter_for(config: CarConfig, config_path: str | Path | None) -> OnnxSegmenter | None:
    """The segmentation model the config names (provider onnx), None for masks from the log."""
    seg = config.mapper.segmentation
    return OnnxSegmenter.load(seg, config_path) if seg.provider == "onnx" else None


def _decode_keyframes(chosen: list[_KeyframeMessages], segmenter: OnnxSegmenter | None,
                      progress: bool = False) -> list[Keyframe]:
    keyframes = []
    for k in tqdm(chosen, desc="keyframes", unit="frame", disable=not progress, mininterval=0.5):
        image = decode_image(k.frame)
        keyframes.append(Keyframe(k.camera, k.timestamp, k.T_world_camera, image,
                                  keyframe_semantics(image, k.mask, segmenter)))
    return keyframes
