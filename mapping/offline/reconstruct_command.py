"""`roadlog reconstruct LOG... --out DIR`: EMIE-MAP on recorded drive logs, with the paper's metrics.

The car's config comes from the logs' own metadata unless --config names one. With --gt (a simulated
drive's PATH.gt.npz) the map is also measured against the truth: `elev_mae_gt_cm` against the true
elevation grid and `miou_pct` against the true semantic grid (bird's-eye view, cells the map observed);
without it `miou_pct` compares rendered semantics with the segmentation masks of held-out frames.

A log without masks (and no segmentation model configured) still maps: colour and elevation from every frame,
no semantics (`miou_pct` null, `semantics` says why, no bev_semantics.* files), and a warning on stderr naming
the frames without a mask. When only some frames have masks, the semantics come from those.

`--pose-refinement on|off|photometric|lidar` switches the fast fit's pose corrections (mapper.pose_refinement;
photometric: without the Lidar ground registration first; lidar: every axis from the Lidar ground, its heights and
intensity contrast, no photometric fit: `lidar_horizontal`). `--pose-noise-m` /
`--pose-noise-deg` (benches) inject a smooth random error into the trajectory before anything is placed with it
(mapping.localization.pose_noise); metrics `pose_noise` then give it and what the corrections left of it.
"""

from __future__ import annotations

import argparse
import atexit
import json
import shutil
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from daemon.log_format.reader import not_a_log, read_metadata
from daemon.spine.config import (
    CarConfig,
    ConfigError,
    config_to_yaml,
    load_config,
    parse_config,
    reports_config_errors,
)
from daemon.spine.health import process_memory_mb
from daemon.spine.local_frame import LocalFrame
from daemon.spine.recorded_config import known_mapper_keys, sectioned_recorded_config
from daemon.spine.yaml_document import UnusableYaml, load_yaml
from mapping.fits.lidar_horizontal_registration import register_horizontal
from mapping.fits.lidar_registration import register_ground
from mapping.fits.pose_refinement import PoseCorrections, corrected_trajectory
from mapping.fits.reconstruction import ReconstructionResult, lidar_refinement_unavailable, reconstruct
from mapping.inputs.drive_inputs import DriveInputs, missing_masks_warning, start_loading_drive
from mapping.localization.pose_noise import PoseNoise, residual_error
from mapping.localization.trajectory import HorizontalTrack, Trajectory
from mapping.method.compute_device import DEVICES, resolve_device, with_device
from mapping.method.road_map import ABLATIONS, variant_for
from mapping.method.scene_data import GroundTruth


@dataclass(frozen=True)
class DriveTruth:
    """A simulated drive's ground truth (sim/drive_log writes it beside the log)."""

    origin: LocalFrame
    elevation: GroundTruth  # the true elevation and semantic grids
    lidar_points: np.ndarray  # (N, 3) true road-surface points hit by the Lidar

    @property
    def semantic(self) -> np.ndarray:
        return self.elevation.semantic

    def in_frame(self, frame: LocalFrame, tolerance_m: float = 0.001) -> DriveTruth:
        """The same truth in another local frame near this one (a map's own, its origin the drive's first fix):
        the grids and points moved by the offset between the two origins. Two ENU frames a few hundred metres
        apart differ by a rotation of about their distance over the earth's radius; where that would move a
        corner of the grid by more than `tolerance_m`, a ValueError."""
        if frame == self.origin:
            return self
        gt = self.elevation
        offset = frame.geodetic_to_enu(*self.origin.enu_to_geodetic(np.zeros((1, 3))))[0]
        h, w = gt.elevation_m.shape
        corners = np.array([[gt.origin_xy[0] + x * gt.resolution_m, gt.origin_xy[1] + y * gt.resolution_m, 0.0]
                            for x in (0, w - 1) for y in (0, h - 1)])
        error = np.abs(frame.geodetic_to_enu(*self.origin.enu_to_geodetic(corners)) - (corners + offset)).max()
        if error > tolerance_m:
            raise ValueError(f"the truth moved into {frame} is off by {100 * error:.1f} cm at its corners: the "
                             f"frames are too far apart for a translation")
        moved = GroundTruth(gt.elevation_m + np.float32(offset[2]), (gt.origin_xy[0] + offset[0],
                            gt.origin_xy[1] + offset[1]), gt.resolution_m, gt.semantic)
        return DriveTruth(frame, moved, self.lidar_points + offset)

    @staticmethod
    def load(path: str | Path) -> DriveTruth:
        """The truth file; one that is missing or not a simulated drive's truth is a ConfigError."""
        try:
            gt = np.load(path)
            return DriveTruth._of(gt)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:  # missing, not an .npz, other arrays
            raise ConfigError(f"--gt {path}: not a simulated drive's ground truth (PATH.gt.npz): "
                              f"{getattr(exc, 'strerror', None) or exc}") from None

    @staticmethod
    def _of(gt) -> DriveTruth:
        res = float(gt["grid_resolution_m"])
        origin_xy = tuple(float(v) + res / 2 for v in gt["grid_origin_xy"])  # the file gives cell corners
        return DriveTruth(LocalFrame(*(float(v) for v in gt["enu_origin_lat_lon_alt"])),
                          GroundTruth(gt["elevation"].astype(np.float32), origin_xy, res, gt["semantic"]),
                          gt["lidar_points_enu"])


def say(line: str) -> None:
    """One `roadlog reconstruct: ...` line on stderr, on a line of its own even while progress bars run (the Lidar
    ground's and the keyframes' run in the background, beside the fit's)."""
    tqdm.write(f"roadlog reconstruct: {line}", file=sys.stderr)
    sys.stderr.flush()


class PhaseLines:
    """One stderr line as each phase of a reconstruction ends: `roadlog reconstruct: [  12.3 s] PHASE (+4.1 s)`,
    the time since the start and the phase's own."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.started = self.last = time.perf_counter()

    def __call__(self, what: str) -> None:
        now = time.perf_counter()
        if self.enabled:
            say(f"[{now - self.started:7.1f} s] {what} (+{now - self.last:.1f} s)")
        self.last = now


def config_from_logs(paths: list[str]) -> tuple[CarConfig, Path]:
    """The car config recorded in the first log, and a file holding its Lidar metadata (if recorded)."""
    meta = read_metadata(paths[0]).get("roadlog", {})
    if "config" not in meta:
        raise ConfigError(f"{paths[0]}: no recorded config in the log metadata; pass --config")
    try:
        recorded, dropped = known_mapper_keys(sectioned_recorded_config(load_yaml(meta["config"].encode())))
    except UnusableYaml as exc:
        raise ConfigError(f"{paths[0]}: recorded config: {exc}") from None
    if dropped:
        say(f"warning: {paths[0]}: the recorded config's mapper keys {', '.join(dropped)} are unknown to this "
            f"version (renamed or removed): ignored, today's defaults apply")
    config = parse_config(recorded, f"{paths[0]} (recorded config)")
    folder = Path(tempfile.mkdtemp(prefix="roadlog-reconstruct-"))  # lives as long as this process
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    packets = config.sensors.lidar is not None and not config.sensors.lidar.point_clouds  # decoded with metadata
    if packets and "lidar_metadata" not in meta:
        raise ConfigError(f"{paths[0]}: the recorded config has a Lidar but the log holds no Lidar metadata "
                          f"({meta.get('lidar_metadata_error', 'not recorded')}); pass --config")
    if packets:
        (folder / Path(config.sensors.lidar.metadata_file).name).write_text(meta["lidar_metadata"])
        config = config.model_copy(update={"sensors": config.sensors.model_copy(update={
            "lidar": config.sensors.lidar.model_copy(update={"metadata_file": Path(
                config.sensors.lidar.metadata_file).name})})})
    return config, folder / "car.yaml"


def run_reconstruction(logs: list[str], out: Path, config: CarConfig, config_path: Path, *,
                       truth: DriveTruth | None = None, use_lidar: bool = True, ablation: str | None = None,
                       faithful: bool = False, progress: bool = True,
                       pose_noise: PoseNoise | None = None) -> tuple[ReconstructionResult, DriveInputs]:
    started = time.perf_counter()
    phase = PhaseLines(progress)
    phase(f"reading {len(logs)} log(s) in the background, writing to {out}")
    refine = config.mapper.pose_refinement
    pre_pass = None
    if refine.enabled and refine.lidar_horizontal and use_lidar and not faithful \
            and variant_for(ablation).lidar_supervision:
        pre_pass = lidar_pre_pass(logs, config, config_path, truth, progress, pose_noise, phase)
        if pre_pass is not None:  # the drive is read again with the corrected trajectory, nothing fitted twice
            config = config.model_copy(update={"mapper": config.mapper.model_copy(
                update={"pose_refinement": refine.model_copy(update={"enabled": False})})})
    unavailable = None if faithful or pre_pass is not None else lidar_refinement_unavailable(
        refine, variant_for(ablation).lidar_supervision, False, False)  # no pre-pass: no usable Lidar ground
    if unavailable is not None:  # reconstruct reports it too, in metrics pose_refinement.lidar_unavailable
        say(f"warning: --pose-refinement lidar (mapper.pose_refinement.lidar_horizontal) asked for, but "
            f"{unavailable}: the photometric refinement instead")
    loading = start_loading_drive(logs, config, config_path, origin=truth.origin if truth else None,
                                  use_lidar=use_lidar, progress=progress, pose_noise=pose_noise,
                                  trajectory_correction=None if pre_pass is None else pre_pass.correct)
    phase("drive path read")
    warning = missing_masks_warning(loading.counts["frames"], loading.counts["frames_without_mask"])
    if warning is not None:
        say(f"warning: {warning}")
    views = loading.counts.get("lidar_view_clouds")
    if views:
        say(f"warning: the logs hold no Lidar packets, only {views} viewing clouds (lidar/view, "
            f"recorder.point_cloud_view_hz): the Lidar ground is taken from those")
    result = reconstruct(loading.keyframes, loading.cameras, loading.path, loading.lidar_ground_points,
                         config.mapper, config.vehicle.reference_height_m, out_dir=out, ablation=ablation,
                         gt=truth.elevation if truth else None, faithful=faithful, progress=progress,
                         lidar_standing=loading.lidar_standing, origin=loading.trajectory.local_frame,
                         phase=phase, lidar_ground_times=loading.lidar_ground_times,
                         lidar_ground_contrast=loading.lidar_ground_contrast)
    drive = loading.result()
    lidar = drive.lidar_ground_points
    metrics = result.metrics
    if truth is not None:
        if lidar is None:  # Elev-error still needs Lidar ground points: the true ones
            from mapping.outputs.map_metrics import elev_error_cm

            metrics["elev_error_cm"] = elev_error_cm(result.road_map, truth.lidar_points)
    if pre_pass is not None:
        result = replace(result, pose_corrections=pre_pass.corrections)
        metrics.update(pre_pass.timings, lidar_registration=pre_pass.height_figures,
                       lidar_horizontal_registration=pre_pass.horizontal_figures,
                       pose_refinement={**pre_pass.corrections.figures(),
                                        "source": "Lidar pre-pass (height and horizontal registration), the drive "
                                                  "read again with the corrected trajectory"})
    for line in camera_check_warnings(metrics.get("camera_check", {"cameras": {}})):
        say(f"warning: {line}")
    if pose_noise is not None:
        metrics["pose_noise"] = pose_noise_figures(pose_noise, result, drive,
                                                   None if pre_pass is None else pre_pass.path)
    wall = time.perf_counter() - started
    # the one real-time factor (docs/map-outputs.md): drive seconds over this wall time
    metrics.update(drive_s=drive.drive_s, wall_s=wall, rtf=drive.drive_s / wall if wall > 0 else None,
                   peak_rss_mb=process_memory_mb()["VmHWM"],
                   vertices=result.road_map.mesh.num_vertices, inputs=drive.counts, logs=[str(p) for p in logs],
                   lidar_supervision=lidar is not None and variant_for(ablation).lidar_supervision)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str))
    (out / "config.yaml").write_text(config_to_yaml(config))
    phase("metrics.json and config.yaml written")
    return result, drive


@dataclass(frozen=True)
class LidarPrePass:
    """The pose refinement's Lidar pre-pass (`mapper.pose_refinement.lidar_horizontal`, offline): corrections of
    every axis from the Lidar ground alone (mapping.fits.lidar_registration, then
    mapping.fits.lidar_horizontal_registration), fitted along the trajectory as first read (`path`); the drive is
    then read again with the corrected trajectory, so that the Lidar ground filter, its motion compensation, the
    keyframes and the mesh all take the corrected poses."""

    path: HorizontalTrack
    corrections: PoseCorrections
    height_figures: dict
    horizontal_figures: dict
    timings: dict

    def correct(self, trajectory: Trajectory) -> Trajectory:
        return corrected_trajectory(trajectory, self.path, self.corrections)


def lidar_pre_pass(logs: list[str], config: CarConfig, config_path: Path, truth: DriveTruth | None, progress: bool,
                   pose_noise: PoseNoise | None, phase: Callable[[str], None]) -> LidarPrePass | None:
    """The Lidar pre-pass (LidarPrePass); None when the drive has no Lidar ground points with their times."""
    started = time.perf_counter()
    first = start_loading_drive(logs, config, config_path, origin=truth.origin if truth else None, use_lidar=True,
                                progress=progress, pose_noise=pose_noise)
    first.keyframes.cancel()  # queued behind the Lidar: only the ground points are needed here
    points, seconds = first.lidar_ground_points.result(), first.lidar_ground_times.result()
    contrast = first.lidar_ground_contrast.result() if first.lidar_ground_contrast is not None else None
    if points is None or seconds is None or len(points) == 0 or len(seconds) != len(points):
        return None
    path, refine, timings = first.path, config.mapper.pose_refinement, {}
    height, height_figures = register_ground(points, seconds, path, refine, timings)
    corrections, horizontal_figures = register_horizontal(points, seconds, contrast, path, refine, timings, height)
    timings["lidar_pre_pass_wall_s"] = time.perf_counter() - started
    phase(f"Lidar pre-pass: poses corrected ({corrections.figures()['position_rms_cm']:.1f} cm RMS), reading the "
          f"drive again")
    return LidarPrePass(path, corrections, height_figures, horizontal_figures, timings)


def pose_noise_figures(noise: PoseNoise, result: ReconstructionResult, drive: DriveInputs,
                       path: HorizontalTrack | None = None) -> dict:
    """The injected pose error (metrics `pose_noise`) and the RMS error of the vehicle pose at the keyframes'
    times as the map was made: `keyframes_before` as injected, `keyframes_after` once the pose refinement's
    corrections are applied (None without refinement; `path`: the track they were fitted along, if not the
    drive's own: the Lidar pre-pass's)."""
    seconds = np.array([kf.timestamp for kf in drive.keyframes])
    after = None
    if result.pose_corrections is not None:
        position, rotation = result.pose_corrections.at((path or drive.path).horizontal_distance_at(seconds))
        after = residual_error(noise, drive.trajectory, seconds, position, rotation)
    return {**noise.figures(), "keyframes_before": residual_error(noise, drive.trajectory, seconds),
            "keyframes_after": after}


def camera_check_warnings(figures: dict) -> list[str]:
    """The warnings of metrics' camera_check (mapper.camera_check): a camera with too few keyframe pairs, one whose
    yaw or pitch is off (camera_orientation.significant)."""
    lines = []
    for name, check in figures["cameras"].items():
        if check is None:
            lines.append(f"camera {name}: too few keyframe pairs with an essential matrix for the orientation check")
        elif check["warned"]:
            lines.append(f"camera {name}: its images put it {check['yaw_deg']:+.2f} deg yaw, {check['pitch_deg']:+.2f} "
                         f"deg pitch from where its extrinsics and the poses place it ({check['pairs_used']} keyframe "
                         "pairs)" + (": corrected" if figures["mode"] == "apply"
                                     else "; --camera-check apply corrects the keyframes"))
    return lines


def with_pose_refinement(car: CarConfig, setting: str | None) -> CarConfig:
    """The car config with mapper.pose_refinement from `--pose-refinement on|off|photometric|lidar` (None: as it
    is; photometric: on without the Lidar ground registration; lidar: on with the Lidar's horizontal registration
    too, `lidar_horizontal`)."""
    if setting is None:
        return car
    update = {"enabled": setting != "off"}
    if setting != "off":
        update["lidar_registration"] = setting in ("on", "lidar")
        update["lidar_horizontal"] = setting == "lidar"
    refinement = car.mapper.pose_refinement.model_copy(update=update)
    return car.model_copy(update={"mapper": car.mapper.model_copy(update={"pose_refinement": refinement})})


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog reconstruct", description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", help="MCAP drive log segments")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--config", help="car config (default: the one recorded in the logs)")
    parser.add_argument("--gt", help="ground truth PATH.gt.npz of a simulated drive")
    parser.add_argument("--no-lidar", action="store_true", help="no Lidar elevation supervision")
    parser.add_argument("--ablation", choices=sorted(ABLATIONS), help="switch off one part of EMIE-MAP")
    parser.add_argument("--faithful", action="store_true", help="the paper's full computation (slow)")
    parser.add_argument("--epochs", type=int,
                        help="epochs of the faithful fit (default: the config's mapper.faithful_fit.epochs)")
    parser.add_argument("--device", choices=DEVICES,
                        help="torch device of the fit: auto (cuda when there is a GPU), cpu or cuda (default: the "
                             "config's mapper.device)")
    parser.add_argument("--pose-refinement", choices=("on", "off", "photometric", "lidar"),
                        help="fit corrections of the poses to the map (fast path; default: the config's "
                             "mapper.pose_refinement.enabled); photometric: without the Lidar ground registration; "
                             "lidar: every axis from the Lidar ground (heights and intensity), no photometric fit")
    parser.add_argument("--camera-check", choices=("off", "report", "apply"),
                        help="check each camera's orientation against the poses by its images' epipolar geometry "
                             "(metrics camera_check); apply: correct the keyframes by it before the fit (default: "
                             "the config's mapper.camera_check.mode)")
    parser.add_argument("--pose-noise-m", type=float, default=0.0,
                        help="benches: inject a smooth random pose error of this 3-D RMS (m) into the trajectory")
    parser.add_argument("--pose-noise-deg", type=float, default=0.0,
                        help="benches: ... and of this RMS per rotation axis (degrees)")
    parser.add_argument("--pose-noise-every-s", type=float, default=0.5,
                        help="benches: the injected error's independent draws this far apart in time (s)")
    parser.add_argument("--pose-noise-seed", type=int, default=0, help="benches: the injected error's seed")
    args = parser.parse_args(argv)
    if args.pose_noise_m < 0 or args.pose_noise_deg < 0 or args.pose_noise_every_s <= 0:
        raise ConfigError("--pose-noise-m and --pose-noise-deg must be >= 0, --pose-noise-every-s > 0")
    if args.epochs is not None and args.epochs < 1:  # as mapper.faithful_fit.epochs (model_copy does not validate)
        raise ConfigError(f"--epochs {args.epochs}: must be >= 1")
    noise = (PoseNoise(args.pose_noise_m, args.pose_noise_deg, args.pose_noise_every_s, args.pose_noise_seed)
             if args.pose_noise_m > 0 or args.pose_noise_deg > 0 else None)
    given = load_config(args.config) if args.config else None  # the config's own error first, as every process
    problems = [why for why in map(not_a_log, args.logs) if why]
    if problems:
        raise ConfigError("; ".join(problems))
    truth = DriveTruth.load(args.gt) if args.gt else None
    if args.out.exists() and not args.out.is_dir():  # found now, not after the reconstruction
        raise ConfigError(f"--out {args.out}: a file, not a folder")
    if given is not None:
        config, config_path = given, Path(args.config)
    else:
        config, config_path = config_from_logs(args.logs)
    config = with_pose_refinement(with_device(config, args.device), args.pose_refinement)
    if args.camera_check is not None:
        check = config.mapper.camera_check.model_copy(update={"mode": args.camera_check})
        config = config.model_copy(update={"mapper": config.mapper.model_copy(update={"camera_check": check})})
    source = "--device" if args.device is not None else f"{args.config or args.logs[0]}: mapper.device"
    resolve_device(config.mapper.device, source)  # cuda without a GPU: one error line, exit 2
    if args.epochs is not None:
        faithful_fit = config.mapper.faithful_fit.model_copy(update={"epochs": args.epochs})
        config = config.model_copy(update={"mapper": config.mapper.model_copy(update={"faithful_fit": faithful_fit})})
    result, _ = run_reconstruction(args.logs, args.out, config, config_path, truth=truth,  # ConfigError: exit 2
                                   use_lidar=not args.no_lidar, ablation=args.ablation, faithful=args.faithful,
                                   pose_noise=noise)
    keys = ("psnr_db", "psnr_train_db", "miou_pct", "iou_pct", "semantics", "elev_error_cm", "elev_mae_gt_cm",
            "drive_s", "wall_s", "rtf", "peak_rss_mb", "vertices")
    print(json.dumps({k: result.metrics.get(k) for k in keys}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
