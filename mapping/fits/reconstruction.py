"""The reconstruction's common entry, `reconstruct`: the mesh and the model, the keyframe split (training /
held out), one of the two fits of the same EMIE-MAP model, then evaluation and export.

- fast (default, mapping.fits.fast_fit): the model fitted to what the keyframes saw at each vertex, with the
  paper's losses taken per vertex; one pass over the keyframes.
- faithful (mapping.fits.faithful_fit): the paper's computation, every pixel of every batch image rendered
  against the whole window, each step, for `faithful_fit.epochs` epochs.
The evaluation renders pixels exactly, the same for both.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from daemon.spine.local_frame import LocalFrame
from daemon.spine.mapper_config import MapperConfig, PoseRefinementConfig
from mapping.fits import faithful_fit, fast_fit
from mapping.fits.lidar_horizontal_registration import register_horizontal
from mapping.fits.lidar_occlusion import OcclusionTest
from mapping.fits.lidar_registration import re_placed, register_ground
from mapping.fits.pose_refinement import PoseCorrections, corrected, refine_poses
from mapping.localization.camera_orientation import camera_check_figures, check_orientations, corrected_keyframes
from mapping.localization.keyframe_spacing import spaced_by_distance
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.mesh_location import Located
from mapping.method.road_map import RoadMap, new_road_map, variant_for
from mapping.method.road_mesh import build_road_mesh
from mapping.method.scene_data import CameraModel, GroundTruth, Keyframe, StandingPoints
from mapping.outputs.map_export import export_map
from mapping.outputs.map_metrics import (
    MetricPoints,
    PendingEvaluation,
    finish_evaluation,
    start_evaluation,
    truth_cells,
)


@dataclass
class ReconstructionResult:
    metrics: dict
    road_map: RoadMap
    files: dict[str, Path] = field(default_factory=dict)
    pose_corrections: PoseCorrections | None = None  # mapper.pose_refinement on (the fast path): what was fitted


def select_keyframes(keyframes: list[Keyframe], trajectory: HorizontalTrack, spacing_m: float) -> list[Keyframe]:
    """Per camera, a frame each time the vehicle has moved `spacing_m` (horizontally) since the last kept one;
    in time order."""
    in_time = sorted(keyframes, key=lambda k: k.timestamp)

    def travelled(kf: Keyframe) -> float:
        return float(trajectory.horizontal_distance_at(kf.timestamp))

    kept = set()
    for camera in dict.fromkeys(kf.camera for kf in in_time):
        mine = [kf for kf in in_time if kf.camera == camera]
        kept.update(id(kf) for kf in spaced_by_distance(mine, travelled, spacing_m))
    return [kf for kf in in_time if id(kf) in kept]


def semantics_status(train: list[Keyframe], road_map: RoadMap, config: MapperConfig) -> str:
    """What the map's semantics rest on, in words (metrics `semantics`): "available" when every training
    keyframe has semantics (a mask or the model's labels), "partial: ..." when some lack a mask (semantics from
    the others only), "unavailable: ..." when none has one, "off: ..." under the no-semantics ablation."""
    if road_map.semantic_logits is None:
        return "off: the ablation has no semantics"
    missing = sum(k.semantics is None for k in train)
    if missing == 0:
        return "available"
    why = (f"{missing} of {len(train)} training keyframes have no mask and no segmentation model is configured "
           f"(mapper.segmentation.provider: {config.segmentation.provider})")
    if missing == len(train):
        return f"unavailable: {why}"
    return f"partial: {why}; semantics from the other {len(train) - missing}"


CONSENSUS_WORDS = ("; colours: the consensus of the views (mapping.fits.colour_consensus), the views that disagree "
                   "with it left out")


def maskless_figures(reads: int, hidden: int, unchecked: int, occlusion: OcclusionTest | None,
                     consensus: bool = False) -> dict:
    """What was left out of the views without semantics (metrics): `maskless_rejection` in words,
    `maskless_hidden_pct` of their colour reads (pixels, faithful) found hidden by what the Lidar saw standing
    on the road, `maskless_views_unchecked`: those with no Lidar scan near enough in time to test. `consensus`:
    the fast fit took their colours' consensus (the share left out: `maskless_disagreeing_pct`)."""
    words = CONSENSUS_WORDS if consensus else ""
    if occlusion is None:
        return {"maskless_rejection": "none: no Lidar standing points (no Lidar, --no-lidar, or "
                                      "mapper.maskless.lidar_occlusion false): what stands on the road in view "
                                      "reaches the colours" + (" unless the other views disagree" + words
                                                               if consensus else ""),
                "maskless_hidden_pct": None, "maskless_views_unchecked": 0}
    return {"maskless_rejection": "lidar occlusion: surface points hidden in a view by what the Lidar scan nearest "
                                  "in time saw standing on the road (mapping.fits.lidar_occlusion) are left out"
                                  + words,
            "maskless_hidden_pct": 100.0 * hidden / reads if reads else None, "maskless_views_unchecked": unchecked}


def _waited_for(value, timings: dict[str, float], key: str):
    """An input that may still be in preparation (a Future: mapping.inputs.drive_inputs.LoadingDrive), once ready;
    the wait goes into `timings`."""
    if not isinstance(value, Future):
        return value
    started = time.perf_counter()
    ready = value.result()
    timings[key] = time.perf_counter() - started
    return ready


def lidar_refinement_unavailable(refine: PoseRefinementConfig, lidar_supervision: bool, have_lidar: bool,
                                 registered: bool) -> str | None:
    """Why the Lidar registration of every axis (`mapper.pose_refinement.lidar_horizontal`), asked for, did not
    run, so that the photometric refinement took its place (metrics `pose_refinement.lidar_unavailable`); None when
    it was not asked for. `registered`: the height registration ran (the ground points had their firing times)."""
    if not (refine.enabled and refine.lidar_horizontal):
        return None
    if not lidar_supervision:
        return "the ablation fits without Lidar supervision"
    if not have_lidar:
        return "no Lidar ground points (a drive without Lidar, or --no-lidar)"
    if not registered:
        return "the Lidar ground points have no firing times"
    return None


def reconstruct(
    keyframes: list[Keyframe] | Future[list[Keyframe]],
    cameras: dict[str, CameraModel],
    trajectory: HorizontalTrack,
    lidar_ground_points: np.ndarray | None | Future[np.ndarray | None],
    config: MapperConfig,
    reference_height_m: float,
    out_dir: Path | None = None,
    ablation: str | None = None,
    gt: GroundTruth | None = None,
    faithful: bool = False,
    holdout_every: int = 10,
    progress: bool = True,
    lidar_standing: StandingPoints | None | Future[StandingPoints | None] = None,
    origin: LocalFrame | None = None,
    phase: Callable[[str], None] = lambda _: None,
    lidar_ground_times: np.ndarray | None | Future[np.ndarray | None] = None,
    lidar_ground_contrast: np.ndarray | None | Future[np.ndarray | None] = None,
) -> ReconstructionResult:
    """Reconstruct the road surface seen by `keyframes` along `trajectory`; evaluate; export if out_dir.
    `keyframes`, `lidar_ground_points` and `lidar_standing` may be Futures (inputs still loading): the mesh is
    built first, the Lidar waited for by the elevation fit, the keyframes after it. `lidar_standing`: what the
    Lidar saw standing on the road, which the keyframes without semantics are tested against
    (mapping.fits.lidar_occlusion; None: they are used whole). `origin`: the geodetic origin of the trajectory's
    ENU frame, which places the exported map on the earth (None: unknown). `phase` is told each phase as it ends.
    `lidar_ground_times`: each ground point's firing time (s from the track's start), which the pose refinement's
    Lidar registration needs (None: photometric refinement only). `lidar_ground_contrast`: each ground point's
    intensity contrast, which its horizontal registration aligns (`mapper.pose_refinement.lidar_horizontal`; None:
    the heights only)."""
    start = time.perf_counter()
    runtime, model, windows = config.runtime, config.model, config.windows
    torch.set_num_threads(runtime.torch_threads_faithful_fit if faithful else runtime.torch_threads_fast_fit)
    torch.manual_seed(model.seed)
    rng = np.random.default_rng(model.seed)
    variant = variant_for(ablation)
    mesh = build_road_mesh(trajectory, config.mesh.corridor_half_width_m, config.mesh.side_m, reference_height_m,
                           flat=variant.flat_init)
    generator = torch.Generator().manual_seed(model.seed)
    road_map = new_road_map(
        mesh, variant, sorted(cameras), model.colour_code_dim, model.colour_mlp_layers, model.colour_mlp_width,
        model.positional_encoding_dim, model.elevation_mlp_layers, model.elevation_mlp_width,
        windows.before_m + windows.after_m, 0.0 if faithful else config.fast_fit.elevation_lattice_m, generator,
    )
    history = []
    timings: dict[str, float] = {"setup_wall_s": time.perf_counter() - start}
    phase(f"mesh and model built ({mesh.num_vertices} vertices)")
    lidar_ground_points = _waited_for(lidar_ground_points, timings, "lidar_wait_s")
    phase("Lidar ground points read" if lidar_ground_points is not None else "no Lidar ground points")
    supervision = lidar_ground_points if variant.lidar_supervision else None
    # the truth cells are placed on the mesh beside the Lidar points (numpy releases the GIL), which the
    # elevation fit, the Lidar detail and the metrics share
    side = ThreadPoolExecutor(1, thread_name_prefix="reconstruct-side")
    evaluation: PendingEvaluation | None = None
    try:
        truth_at = side.submit(Located.of, mesh, truth_cells(gt)[2]) if gt is not None else None
        have_lidar = lidar_ground_points is not None and len(lidar_ground_points) > 0
        lidar_corrections, lidar_figures, horizontal_figures = None, None, None
        refine = config.pose_refinement
        if not faithful and refine.enabled and refine.lidar_registration and have_lidar \
                and variant.lidar_supervision:
            ground_times = _waited_for(lidar_ground_times, timings, "lidar_times_wait_s")
            if ground_times is not None and len(ground_times) == len(lidar_ground_points):
                lidar_corrections, lidar_figures = register_ground(lidar_ground_points, ground_times, trajectory,
                                                                   refine, timings)
                if refine.lidar_horizontal:  # all six axes from the Lidar, from the heights' corrections
                    contrast = _waited_for(lidar_ground_contrast, timings, "lidar_contrast_wait_s")
                    if contrast is not None and len(contrast) != len(lidar_ground_points):
                        contrast = None
                    lidar_corrections, horizontal_figures = register_horizontal(
                        lidar_ground_points, ground_times, contrast, trajectory, refine, timings, lidar_corrections)
                    phase(f"Lidar ground registered horizontally ({horizontal_figures['position_rms_cm']:.1f} cm "
                          f"RMS correction)")
                lidar_ground_points = re_placed(lidar_ground_points, ground_times, trajectory, lidar_corrections)
                supervision = lidar_ground_points
                phase(f"Lidar ground registered ({lidar_figures['position_rms_cm']:.1f} cm RMS height correction)")
        lidar_at = Located.of(mesh, lidar_ground_points[:, :2]) if have_lidar else None
        if not faithful:  # the elevation needs the Lidar only: it is fitted while the images may still be decoding
            elevation_first_last = fast_fit.fit_surface(road_map, supervision, lidar_at, config, rng, timings,
                                                        progress)
            phase("elevation fitted")
        selected = select_keyframes(_waited_for(keyframes, timings, "keyframes_wait_s"), trajectory,
                                    config.inputs.keyframe_spacing_m)
        holdout = [k for i, k in enumerate(selected) if holdout_every > 0 and i % holdout_every == holdout_every // 2]
        held = {id(k) for k in holdout}
        train = [k for k in selected if id(k) not in held]
        phase(f"camera frames read: {len(selected)} keyframes selected, {len(train)} to train on")
        if not train:
            raise ValueError(f"no training keyframes after selection (of {len(selected)} keyframes selected)")
        camera_checks = None
        if config.camera_check.mode != "off":  # fitted on the training views, a calibration of every view
            camera_checks = check_orientations(train, cameras, config.camera_check)
            if config.camera_check.mode == "apply":
                train, holdout = (corrected_keyframes(views, camera_checks, config.camera_check)
                                  for views in (train, holdout))
            phase("camera orientations checked against the poses"
                  + (" and corrected" if config.camera_check.mode == "apply" else ""))
        if not faithful and supervision is None and not variant.flat_init:  # camera-only: from the images
            elevation_first_last = fast_fit.fit_surface_from_images(road_map, train, cameras, trajectory, config,
                                                                    rng, timings, progress)
        corrections, pose_figures = None, None
        lidar_unavailable = None if faithful or horizontal_figures is not None else lidar_refinement_unavailable(
            config.pose_refinement, variant.lidar_supervision, have_lidar, lidar_figures is not None)
        if horizontal_figures is not None:  # the Lidar fitted every axis: the cameras take its corrections
            corrections = lidar_corrections
            train, holdout = corrected(train, trajectory, corrections), corrected(holdout, trajectory, corrections)
            pose_figures = {**corrections.figures(), "source": "lidar registration (height and horizontal)"}
        elif not faithful and config.pose_refinement.enabled:  # the corrected poses observe and are evaluated
            train, holdout, corrections, pose_figures = refine_poses(
                road_map, train, holdout, cameras, trajectory, config.pose_refinement, config.fast_fit.behind_m,
                config.fast_fit.ahead_m, timings, lidar_corrections)
            if lidar_unavailable is not None:  # asked for the Lidar's every axis, given the photometric fit
                pose_figures.update(source="photometric", lidar_unavailable=lidar_unavailable)
            phase(f"poses refined ({pose_figures['position_rms_cm']:.1f} cm RMS correction)")
        semantics = semantics_status(train, road_map, config)
        if semantics.startswith("unavailable"):  # nothing to train them on: no semantics, not untrained logits
            road_map.semantic_logits = None
        maskless = any(k.semantics is None for k in train)
        occlusion = OcclusionTest.of(_waited_for(lidar_standing, timings, "standing_wait_s"), config.maskless)
        evaluation_args = (cameras, holdout, train, trajectory, lidar_ground_points, gt, windows.before_m,
                           windows.after_m, runtime.evaluation_threads)
        metric_points = MetricPoints(lidar_at, truth_at.result() if truth_at is not None else None)
        if faithful:
            history, last_epoch_steps, tested = faithful_fit.fit_faithful(
                road_map, cameras, train, trajectory, supervision, lidar_at, config, rng, progress, occlusion)
            phase("faithful fit done")
            evaluation = start_evaluation(road_map, *evaluation_args, metric_points)
        else:
            obs = fast_fit.observe(road_map, train, cameras, trajectory, config, progress, timings, occlusion)
            tested = (obs.maskless_reads, obs.maskless_hidden, obs.maskless_unchecked)
            phase("keyframes observed")
            # surface and semantics are final: the evaluation renders its views beside the colour fit
            evaluation = start_evaluation(road_map, *evaluation_args, metric_points)
            colour_first, colour_last = fast_fit.fit_colour(road_map, obs, config, rng, timings, progress)
            history = [elevation_first_last[0] + colour_first, elevation_first_last[1] + colour_last]
            phase("colour fitted")
            last_epoch_steps = 1
        train_s = time.perf_counter() - start
        drive_s = trajectory.duration_s
        # the export runs beside the evaluation's remaining work: both only read the finished map
        exported = (side.submit(export_map, road_map, Path(out_dir), sorted(cameras), runtime.raster_threads,
                                origin)
                    if out_dir is not None else None)
        side.shutdown(wait=False)
        metrics = finish_evaluation(evaluation)
        evaluate_s = time.perf_counter() - start - train_s
        phase("evaluated on the held-out views")
        files: dict[str, Path] = exported.result() if exported is not None else {}
        phase("map exported (rasters, mesh, checkpoint)" if exported is not None else "done")
    except BaseException:  # a failed reconstruction leaves no queued background work (the worker retries)
        side.shutdown(wait=False, cancel_futures=True)
        if evaluation is not None:
            evaluation.pool.shutdown(wait=False, cancel_futures=True)
        raise
    metrics.update(
        ablation=ablation or "none",
        path="faithful" if faithful else "fast",
        keyframes_train=len(train),
        keyframes_holdout=len(holdout),
        semantics=semantics,
        keyframes_without_semantics=sum(k.semantics is None for k in selected),
        steps=len(history),
        vertices=mesh.num_vertices,
        vertices_observed=int((road_map.observed > 0).sum()),
        loss_first=history[0] if history else None,
        loss_last=float(np.mean(history[-last_epoch_steps:])) if history else None,
        optimise_wall_s=train_s,
        evaluate_wall_s=evaluate_s,
        **timings,
        step_mean_s=(train_s - timings["setup_wall_s"]) / max(1, len(history)),
        drive_s=drive_s,
        **(maskless_figures(*tested, occlusion, not faithful and config.maskless.consensus) if maskless else {}),
        **({"pose_refinement": pose_figures} if pose_figures is not None else {}),
        **({"camera_check": camera_check_figures(camera_checks, config.camera_check)}
           if camera_checks is not None else {}),
        **({"lidar_registration": lidar_figures} if lidar_figures is not None else {}),
        **({"lidar_horizontal_registration": horizontal_figures} if horizontal_figures is not None else {}),
    )
    if out_dir is not None:
        path = Path(out_dir) / "metrics.json"
        path.write_text(json.dumps(metrics, indent=2))
        files["metrics"] = path
    return ReconstructionResult(metrics, road_map, files, corrections)

