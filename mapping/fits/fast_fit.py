"""The fast fit (the default): the EMIE-MAP model fitted to what the keyframes saw at each vertex instead of to
rendered pixels. The elevation MLP on a lattice against the Lidar ground points, then the Lidar detail
(mapping.fits.lidar_detail); every keyframe projected onto the vertices in its reach
(mapping.fits.vertex_observations), which sets the semantics from the label frequencies; the colour codes and
per-camera decoders fitted to each camera's mean colour (mapping.fits.observation_fit). One pass over the
keyframes instead of epochs of rendering."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from daemon.spine.config import MapperConfig
from mapping.fits.lidar_detail import fit_lidar_detail
from mapping.fits.observation_fit import fit_colours, fit_elevation, semantic_logits_from_counts
from mapping.fits.vertex_observations import MeshFootprint, VertexObservations, observe_keyframe
from mapping.method.mesh_location import Located
from mapping.method.road_map import RoadMap, WindowIndex
from mapping.method.scene_data import CameraModel, Keyframe, Trajectory


@dataclass(frozen=True)
class FastPathSettings:
    elevation_lattice_m: float = 1.0  # residual MLP lattice; 0 = at every vertex. The Lidar detail carries what
    # is finer than the lattice: over seeds 0-2, 1.0 m against 0.5 m: city31 mIoU 89.70 / 89.70 %, PSNR 28.86 /
    # 28.88 dB, MAE vs truth 1.351 / 1.347 cm; ramp30 89.82 / 89.92 %, 28.30 / 28.24 dB, 2.36 / 2.30 cm; the fit
    # 5.1 s instead of 7.5 s on city31 (a quarter of the nodes: the minimum of 150 steps now sets its length)
    elevation_epochs: float = 5.0  # passes over the Lidar lattice nodes of the elevation fit (8 before the Lidar
    # detail: with it, 5 epochs give the same maps: city31 89.8 % / 28.90 dB / 0.43 cm, ramp30 89.9 % / 27.99 dB /
    # 0.73 cm / 2.30 cm vs truth, against 8 epochs' 89.8 / 28.97 / 0.43 and 89.9 / 28.03 / 0.73 / 2.29; 3 epochs
    # 89.6 % / 28.75 dB on city31) ...
    elevation_min_steps: int = 150  # ... but at least this many Adam steps (short drives)
    elevation_batch: int = 512  # lattice nodes per elevation step ...
    elevation_smooth_pairs: int = 128  # ... and neighbour pairs for the smoothness term. Against 3 epochs with
    # 512 pairs and no decay, on city31 (same fit time, 12.6 vs 14.6 s under load): Elev-error 1.25 -> 0.73 cm,
    # MAE vs truth 1.71 -> 1.42 cm, bird's-eye mIoU 72.1 -> 78.4 (labels land where the curbs really are)
    behind_m: float = 3.0  # a keyframe observes vertices from this far behind its trajectory point ...
    ahead_m: float = 12.0  # ... to this far ahead: far views blur. city31 (elevation fit as above): 20 m psnr
    # 27.72 dB, bird's-eye mIoU 78.4; 12 m 28.87 dB, 78.3; 8 m 28.29 dB, 77.4
    lidar_detail_passes: int = 8  # Jacobi passes of the Lidar detail (mapping.fits.lidar_detail); 0 = none.
    # city10, bird's-eye mIoU: none 80.9 %; prior 0.3: 85.4, 0.1: 85.9, 0.03: 86.3; PSNR and Elev-error
    # no worse (28.67 -> 28.65 dB, 0.62 -> 0.34 cm), MAE vs truth 1.60 -> 1.53 cm
    lidar_detail_prior: float = 0.03  # points' worth of zero detail at each vertex
    label_sharp_m: float | None = 0.01  # labels count fully where a pixel covers at most this much ground
    # along the line of sight, in proportion beyond (mapping.fits.vertex_observations.label_weights; None: all
    # count 1). Bird's-eye mIoU, seeds 0-2, all equal against 0.01 m: city31 89.69-89.70 / 90.25-90.28 %
    # (lane marking 81.2 -> 82.1, manhole 87.6-88.2 -> 89.6-90.1); seed 0: ramp30 90.96 / 91.84 %, night31
    # 89.94 / 90.82 %; PSNR and elevation unchanged (labels only). 0.02 m
    # gave city31 89.96-90.00 %; 0.005 / 0.0025 m 90.26-90.30 / 90.37-90.42 %: the same weights, only scaled
    # down against the label prior (observation_fit.LABEL_PRIOR, a separate knob, left as tuned).
    colour_encoder_steps: int = 200  # joint encoder/decoder steps on a sample of vertices
    colour_batch: int = 4096
    lr_encoder: float = 0.01
    threads_observe: int = 2  # Python threads observing keyframes (city31: 5.9 -> 3.2 s)
    threads: int = 1  # torch threads of the fast path (fits and evaluation): its MLPs are small, and on this
    # 2-core machine 2 threads ran the elevation fit 8x slower than 1 (59 s vs 7 s), worse under load


def fit_surface(road_map: RoadMap, supervision: np.ndarray | None, lidar_at: Located | None, config: MapperConfig,
                fast: FastPathSettings, rng: np.random.Generator, timings: dict[str, float]) -> tuple[float, float]:
    """The elevation: the residual MLP fitted to the Lidar lattice (mapping.fits.observation_fit), then the Lidar
    detail; the weighted loss of the elevation fit's first and last step. `supervision`: the Lidar ground points
    (None: none, or an ablation without them), `lidar_at`: the ground points placed on the mesh."""
    started = time.perf_counter()
    elevation_first_last = _fit_elevation(road_map, supervision, lidar_at, config, fast, rng)
    timings["elevation_fit_wall_s"] = time.perf_counter() - started
    if road_map.elevation is not None and supervision is not None and len(supervision) and fast.lidar_detail_passes:
        started = time.perf_counter()
        detail = fit_lidar_detail(road_map.z_now, lidar_at, supervision[:, 2], fast.lidar_detail_passes,
                                  fast.lidar_detail_prior)
        timings["lidar_detail_wall_s"] = time.perf_counter() - started
        timings["lidar_detail_mean_cm"] = 100.0 * float(np.abs(detail).mean())
    return elevation_first_last


def _fit_elevation(road_map: RoadMap, lidar: np.ndarray | None, located: Located | None, config: MapperConfig,
                   fast: FastPathSettings, rng: np.random.Generator) -> tuple[float, float]:
    """The fast path's elevation: the residual MLP fitted to the Lidar lattice (mapping.fits.observation_fit);
    the weighted loss of its first and last step."""
    if road_map.elevation is None or lidar is None or not len(lidar):
        return 0.0, 0.0
    lr, w = config.learning_rates, config.loss_weights
    first_last = fit_elevation(road_map, lidar, located, fast.elevation_lattice_m, fast.elevation_epochs,
                               fast.elevation_min_steps, fast.elevation_batch, fast.elevation_smooth_pairs,
                               lr.elevation_mlp, w.elevation, w.smoothness, rng)
    road_map.refresh_elevation()
    return first_last


def observe(road_map: RoadMap, train: list[Keyframe], cameras: dict[str, CameraModel], trajectory: Trajectory,
            fast: FastPathSettings, progress: bool, timings: dict[str, float]) -> VertexObservations:
    """Every keyframe's view of every vertex in reach; sets the vertices' observation counts and semantics."""
    started = time.perf_counter()
    mesh = road_map.mesh
    windows = WindowIndex.of(mesh)
    bar = tqdm(total=len(train), desc="observe", disable=not progress, unit="frame")

    def observe_part(keyframes: list[Keyframe]) -> VertexObservations:
        part = VertexObservations.empty(mesh.num_vertices, road_map.decoder.camera_names)
        footprint = MeshFootprint.of(mesh.neighbours)
        for kf in keyframes:
            s = float(trajectory.along_track_at(kf.timestamp))
            a, b = np.searchsorted(windows.vertex_s, [s - fast.behind_m, s + fast.ahead_m])
            ids = windows.vertex_order[a:b]
            points = np.concatenate([mesh.xy[ids], road_map.z_now[ids, None].astype(np.float64)], 1)
            observe_keyframe(part, ids, points, kf, cameras[kf.camera], footprint, fast.label_sharp_m)
            bar.update()
        return part

    # two threads (numpy releases the GIL in its array work), each keyframe half into its own observations,
    # added in a fixed order: the same sums whatever the threads' timing
    with ThreadPoolExecutor(fast.threads_observe) as pool:
        parts = list(pool.map(observe_part, [train[i::fast.threads_observe] for i in range(fast.threads_observe)]))
    bar.close()
    obs = parts[0]
    for part in parts[1:]:
        obs.add(part)
    seen = obs.seen
    road_map.observed[seen] = obs.colour_count[seen].sum(1).astype(np.int32)
    if road_map.semantic_logits is not None:
        labelled = np.nonzero(obs.label_counts.sum(1) > 0)[0]
        road_map.semantic_logits[torch.from_numpy(labelled)] = semantic_logits_from_counts(obs.label_counts[labelled])
    timings["observe_wall_s"] = time.perf_counter() - started
    return obs


def fit_colour(road_map: RoadMap, obs: VertexObservations, config: MapperConfig, fast: FastPathSettings,
               rng: np.random.Generator, timings: dict[str, float]) -> tuple[float, float]:
    """Colour codes and decoders fitted to the observations; the colour loss of the first and the last step."""
    seen = obs.seen
    if not len(seen):
        return 0.0, 0.0
    lr = config.learning_rates
    started = time.perf_counter()
    losses_first_last = fit_colours(road_map, obs, seen, fast.colour_encoder_steps, fast.colour_batch,
                                    lr.colour_mlps, fast.lr_encoder, rng)
    timings["colour_fit_wall_s"] = time.perf_counter() - started
    return losses_first_last


