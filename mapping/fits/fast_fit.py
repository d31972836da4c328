"""The fast fit (the default): the EMIE-MAP model fitted to what the keyframes saw at each vertex instead of to
rendered pixels. The elevation MLP on a lattice against the Lidar ground points, then the Lidar detail
(mapping.fits.lidar_detail); every keyframe projected onto the vertices in its reach
(mapping.fits.vertex_observations), which sets the semantics from the label frequencies; the colour codes and
per-camera decoders fitted to each camera's mean colour (mapping.fits.observation_fit). One pass over the
keyframes instead of epochs of rendering."""

from __future__ import annotations

import copy
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import torch
from tqdm import tqdm

from daemon.spine.mapper_config import FastFitConfig, MapperConfig
from mapping.fits.lidar_detail import fit_lidar_detail
from mapping.fits.lidar_occlusion import OcclusionTest
from mapping.fits.mapped_area import mapped_vertices
from mapping.fits.observation_fit import fit_colours, fit_elevation, fit_lattice, semantic_logits_from_counts
from mapping.fits.photometric_elevation import SweepSettings, lattice_nodes, sweep_heights
from mapping.fits.vertex_observations import MeshFootprint, VertexObservations, observe_keyframe
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.compute_device import resolve_device
from mapping.method.mesh_location import Located
from mapping.method.road_map import RoadMap, WindowIndex
from mapping.method.scene_data import CameraModel, Keyframe


def fit_surface(road_map: RoadMap, supervision: np.ndarray | None, lidar_at: Located | None, config: MapperConfig,
                rng: np.random.Generator, timings: dict[str, float], progress: bool = False) -> tuple[float, float]:
    """The elevation: the residual MLP fitted to the Lidar lattice (mapping.fits.observation_fit), then the Lidar
    detail; the weighted loss of the elevation fit's first and last step. `supervision`: the Lidar ground points
    (None: none, or an ablation without them), `lidar_at`: the ground points placed on the mesh."""
    fast = config.fast_fit
    started = time.perf_counter()
    elevation_first_last = _fit_elevation(road_map, supervision, lidar_at, fast, rng, resolve_device(config.device),
                                          progress)
    timings["elevation_fit_wall_s"] = time.perf_counter() - started
    if road_map.elevation is not None and supervision is not None and len(supervision) and fast.lidar_detail_passes:
        started = time.perf_counter()
        detail = fit_lidar_detail(road_map.z_now, lidar_at, supervision[:, 2], fast.lidar_detail_passes,
                                  fast.lidar_detail_prior, config.runtime.lidar_detail_threads, progress,
                                  road_map.mesh.neighbours)
        timings["lidar_detail_wall_s"] = time.perf_counter() - started
        timings["lidar_detail_mean_cm"] = 100.0 * float(np.abs(detail).mean())
    return elevation_first_last


def _fit_elevation(road_map: RoadMap, lidar: np.ndarray | None, located: Located | None, fast: FastFitConfig,
                   rng: np.random.Generator, device: torch.device, progress: bool) -> tuple[float, float]:
    """The fast path's elevation: the residual MLP fitted to the Lidar lattice (mapping.fits.observation_fit);
    the weighted loss of its first and last step."""
    if road_map.elevation is None or lidar is None or not len(lidar):
        return 0.0, 0.0
    first_last = fit_elevation(road_map, lidar, located, fast.elevation_lattice_m, fast.elevation_epochs,
                               fast.elevation_min_steps, fast.elevation_batch, fast.elevation_smooth_pairs,
                               fast.elevation_lr, fast.elevation_loss_weight, fast.smoothness_loss_weight, rng, device,
                               progress)
    road_map.refresh_elevation()
    return first_last


def fit_surface_from_images(road_map: RoadMap, train: list[Keyframe], cameras: dict[str, CameraModel],
                            trajectory: HorizontalTrack, config: MapperConfig, rng: np.random.Generator,
                            timings: dict[str, float], progress: bool = False) -> tuple[float, float]:
    """Camera-only elevation (no Lidar ground): the plane sweep's heights at the lattice nodes
    (mapping.fits.photometric_elevation), the residual MLP fitted to them weighted by their confidence with the
    same loss as the Lidar's; then (`photometric_refine_span_m` > 0) a second, narrow sweep around that surface
    and the MLP fitted again, from its initial weights, to those heights. The weighted loss of the last fit's
    first and last step."""
    fast = config.fast_fit
    if road_map.elevation is None or not fast.photometric_elevation or not fast.elevation_lattice_m or not train:
        return 0.0, 0.0
    settings = SweepSettings(fast.photometric_span_m, fast.photometric_step_m, fast.photometric_patch_m,
                             fast.photometric_patch_samples, fast.photometric_min_views, fast.photometric_min_std,
                             fast.photometric_distinct_m, fast.photometric_behind_m, fast.photometric_ahead_m,
                             config.runtime.photometric_threads)
    lattice = lattice_nodes(road_map, fast.elevation_lattice_m, trajectory)
    keyframe_s = np.array([float(trajectory.horizontal_distance_at(kf.timestamp)) for kf in train])
    initial = copy.deepcopy(road_map.elevation.state_dict())
    passes = [(settings, None)] + ([(replace(settings, span_m=fast.photometric_refine_span_m), True)]
                                   if fast.photometric_refine_span_m > 0 else [])
    timings["photometric_sweep_wall_s"] = timings["elevation_fit_wall_s"] = 0.0
    for pass_settings, on_fit in passes:
        started = time.perf_counter()
        if on_fit:  # the second pass starts the MLP afresh, centred where the first put the surface
            road_map.elevation.load_state_dict(initial)
        sweep = sweep_heights(road_map, lattice, train, keyframe_s, cameras, pass_settings,
                              road_map.z_now.copy() if on_fit else None)
        timings["photometric_sweep_wall_s"] += time.perf_counter() - started
        timings["photometric_nodes_pct"] = 100.0 * float((sweep.confidence > 0).mean()) if len(lattice.xy) else 0.0
        started = time.perf_counter()
        first_last = fit_lattice(road_map, lattice.nodes, sweep.residual, lattice.z0, sweep.confidence,
                                 fast.elevation_lattice_m, fast.elevation_epochs, fast.elevation_min_steps,
                                 fast.elevation_batch, fast.elevation_smooth_pairs, fast.elevation_lr,
                                 fast.elevation_loss_weight, fast.smoothness_loss_weight, rng,
                                 resolve_device(config.device), progress)
        road_map.refresh_elevation()
        timings["elevation_fit_wall_s"] += time.perf_counter() - started
    return first_last


def observe(road_map: RoadMap, train: list[Keyframe], cameras: dict[str, CameraModel], trajectory: HorizontalTrack,
            config: MapperConfig, progress: bool, timings: dict[str, float],
            occlusion: OcclusionTest | None = None) -> VertexObservations:
    """Every keyframe's view of every vertex in reach; sets the vertices' observation counts (of the vertices the
    mapped-area rule keeps: mapping.fits.mapped_area) and semantics (of the vertices a keyframe with semantics
    labelled); the colours of views without semantics are their consensus (mapping.fits.colour_consensus).
    `occlusion`: the test the views without semantics pass their vertices through (mapping.fits.lidar_occlusion)."""
    started = time.perf_counter()
    fast, threads = config.fast_fit, config.runtime.observe_threads
    mesh = road_map.mesh
    windows = WindowIndex.of(mesh)
    bar = tqdm(total=len(train), desc="observe", disable=not progress, unit="frame")

    maskless = config.maskless

    def observe_part(keyframes: list[Keyframe]) -> VertexObservations:
        part = VertexObservations.empty(mesh.num_vertices, road_map.decoder.camera_names, maskless.consensus)
        footprint = MeshFootprint.of(mesh.neighbours, fast.label_footprint_subdivision)
        for kf in keyframes:
            s = float(trajectory.horizontal_distance_at(kf.timestamp))
            a, b = np.searchsorted(windows.vertex_s, [s - fast.behind_m, s + fast.ahead_m])
            ids = windows.vertex_order[a:b]
            points = np.concatenate([mesh.xy[ids], road_map.z_now[ids, None].astype(np.float64)], 1)
            observe_keyframe(part, ids, points, kf, cameras[kf.camera], footprint, fast.label_sharp_m, occlusion,
                             maskless.consensus_near_m)
            bar.update()
        return part

    # threads (numpy releases the GIL in its array work), each its share of the keyframes into its own
    # observations, added in a fixed order: the same sums whatever the threads' timing
    with ThreadPoolExecutor(threads) as pool:
        parts = list(pool.map(observe_part, [train[i::threads] for i in range(threads)]))
    bar.close()
    obs = parts[0]
    for part in parts[1:]:
        obs.add(part)
    kept = len(obs.consensus_reads) if obs.consensus_reads is not None else 0
    obs.fold_consensus(maskless.consensus_tolerance)
    if kept:
        timings["maskless_disagreeing_pct"] = 100.0 * obs.consensus_rejected / kept
    area_started = time.perf_counter()
    views = obs.colour_count.sum(1)
    mapped = np.flatnonzero(mapped_vertices(mesh, views, fast.edge_min_views, fast.edge_opening_m))
    road_map.observed[mapped] = views[mapped].astype(np.int32)
    timings["mapped_area_wall_s"] = time.perf_counter() - area_started
    if road_map.semantic_logits is not None:
        labelled = np.nonzero(obs.label_counts.sum(1) > 0)[0]
        ids = torch.from_numpy(labelled)
        road_map.semantic_logits[ids] = semantic_logits_from_counts(obs.label_counts, mesh.neighbours,
                                                                    fast.lane_line_gain)[ids]
        road_map.labelled[labelled] = True
    timings["observe_wall_s"] = time.perf_counter() - started
    return obs


def fit_colour(road_map: RoadMap, obs: VertexObservations, config: MapperConfig, rng: np.random.Generator,
               timings: dict[str, float], progress: bool = False) -> tuple[float, float]:
    """Colour codes and decoders fitted to the observations; the colour loss of the first and the last step."""
    seen = obs.seen
    if not len(seen):
        return 0.0, 0.0
    fast = config.fast_fit
    started = time.perf_counter()
    losses_first_last = fit_colours(road_map, obs, seen, fast.colour_encoder_steps, fast.colour_batch,
                                    fast.colour_decoder_lr, fast.colour_encoder_lr, rng, resolve_device(config.device),
                                    progress)
    timings["colour_fit_wall_s"] = time.perf_counter() - started
    return losses_first_last


