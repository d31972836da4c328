"""EMIE-MAP optimisation: trajectory-based batches of adjacent keyframes, one Adam per parameter group,
the four losses, then evaluation and export. `reconstruct` is the public entry point.

Two paths compute the same model:
- faithful: each step takes the whole 160 m window: every window vertex goes through the elevation MLP
  and the colour decoders, every pixel of every batch image is rasterised exactly against the full mesh.
- fast (default): the same model fitted to what the keyframes saw at each vertex (each vertex in reach
  of a keyframe projected into it: mapping.fits.vertex_observations) with the paper's losses taken per
  vertex: the elevation MLP on a `elevation_lattice_m` lattice against the Lidar ground points, the
  semantic logits from label frequencies, the colour codes and per-camera decoders against each
  camera's mean colour (mapping.fits.observation_fit). One pass over the keyframes instead of 5 epochs of
  rendering; evaluation renders pixels exactly as for the faithful path.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from daemon.spine.config import MapperConfig
from daemon.spine.semantic_classes import NUM_MAP_CLASSES
from mapping.fits.lidar_detail import fit_lidar_detail
from mapping.fits.observation_fit import fit_colours, fit_elevation, semantic_logits_from_counts
from mapping.fits.vertex_observations import MeshFootprint, VertexObservations, observe_keyframe
from mapping.method import losses
from mapping.method.mesh_renderer import pixel_rays, rasterise, ray_triangle_weights, world_rays
from mapping.method.road_map import RoadMap, WindowIndex, new_road_map, variant_for
from mapping.method.road_mesh import RoadMesh, build_road_mesh
from mapping.method.row_sparse_adam import RowSparseAdam
from mapping.method.scene_data import CameraModel, GroundTruth, Keyframe, Trajectory
from mapping.outputs.map_export import export_map
from mapping.outputs.map_metrics import (
    Located,
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


def select_keyframes(keyframes: list[Keyframe], trajectory: Trajectory, spacing_m: float) -> list[Keyframe]:
    """Per camera, keep a frame each time the vehicle has moved `spacing_m` since the last kept one."""
    kept, last = [], {}
    for kf in sorted(keyframes, key=lambda k: k.timestamp):
        s = float(trajectory.along_track_at(kf.timestamp))
        if kf.camera not in last or s - last[kf.camera] >= spacing_m:
            kept.append(kf)
            last[kf.camera] = s
    return kept


def lidar_vertex_targets(mesh: RoadMesh, points: np.ndarray | None,
                         located: Located | None) -> tuple[np.ndarray, np.ndarray]:
    """Mean height of the Lidar ground points nearest to each vertex: (vertex ids, z targets). `located`: the
    points placed on the mesh."""
    if points is None or len(points) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    ok = located.inside
    nearest = located.ids[ok, np.argmax(located.weights[ok], 1)].astype(np.int64)
    count = np.bincount(nearest, minlength=mesh.num_vertices)
    total = np.bincount(nearest, weights=points[ok, 2], minlength=mesh.num_vertices)
    have = np.nonzero(count)[0]
    return have, (total[have] / count[have]).astype(np.float32)


@dataclass
class _Supervision:
    """One keyframe's pixels used in a step and the triangles they see."""

    keyframe: Keyframe
    camera: CameraModel
    pixels: np.ndarray  # (P,) flat pixel indices
    tri: np.ndarray  # (P, 3) vertex ids


class _Optimisation:
    """The paper-faithful optimisation: every pixel of every batch image rendered exactly against the
    whole 160 m window, every window vertex through the MLPs, each step."""

    def __init__(self, road_map, cameras, config, lidar_ids, lidar_z):
        self.map, self.cameras, self.config = road_map, cameras, config
        self.windows = WindowIndex.of(road_map.mesh)
        self.lidar_ids, self.lidar_z = lidar_ids, lidar_z
        self.lidar_order = np.argsort(road_map.mesh.s[lidar_ids], kind="stable")
        self.lidar_s = road_map.mesh.s[lidar_ids][self.lidar_order]
        self.lookup = np.full(road_map.mesh.num_vertices, -1, np.int64)
        lr = config.learning_rates
        self.optimisers = []
        if road_map.elevation is not None:
            self.optimisers.append(torch.optim.Adam(road_map.elevation.parameters(), lr=lr.elevation_mlp))
        decoder_params = list(road_map.decoder.parameters())
        if decoder_params:
            self.optimisers.append(torch.optim.Adam(decoder_params, lr=lr.colour_mlps))
        self.colour_opt = RowSparseAdam(road_map.colour_params, lr=lr.colour_codes)
        self.semantic_opt = None
        if road_map.semantic_logits is not None:
            self.semantic_opt = RowSparseAdam(road_map.semantic_logits, lr=lr.semantics)

    # -- what each pixel sees -------------------------------------------------------------------
    def exact_supervision(self, kf: Keyframe, faces: np.ndarray) -> _Supervision:
        cam = self.cameras[kf.camera]
        mesh = self.map.mesh
        tri_all = mesh.faces[faces]
        vertices = np.concatenate([mesh.xy, self.map.z_now[:, None].astype(np.float64)], 1)
        grid = rasterise(vertices, tri_all, cam, kf.T_world_camera).ravel()
        labels = kf.semantics.ravel()
        pixels = np.nonzero((grid >= 0) & (labels < NUM_MAP_CLASSES))[0]
        return _Supervision(kf, cam, pixels, tri_all[grid[pixels]])

    # -- one optimisation step ------------------------------------------------------------------
    def step(self, batch: list[Keyframe], s_center: float) -> dict[str, float]:
        cfg = self.config
        s_lo, s_hi = s_center - cfg.window_before_m, s_center + cfg.window_after_m
        window = self.windows.vertices(s_lo, s_hi)
        z = self.map.elevation_of(window)
        self.map.z_now[window] = z.detach().numpy()
        faces = self.windows.faces(s_lo, s_hi)
        sup = [self.exact_supervision(kf, faces) for kf in batch]
        touched = np.unique(np.concatenate([s.tri.ravel() for s in sup]))
        a, b = np.searchsorted(self.lidar_s, [s_lo, s_hi])
        lidar_sel = self.lidar_order[a:b]
        lidar_ids = self.lidar_ids[lidar_sel]
        ids = window
        self.lookup[ids] = np.arange(len(ids))
        try:
            result = self._losses(sup, ids, touched, lidar_ids, self.lidar_z[lidar_sel], z)
        finally:
            self.lookup[ids] = -1
        return result

    def _losses(self, sup, ids, touched, lidar_ids, lidar_z, z=None) -> dict[str, float]:
        rm, w_cfg = self.map, self.config.loss_weights
        z = rm.elevation_of(ids) if z is None else z
        codes = rm.colour_params[ids].clone().requires_grad_(True)
        logits_v = None
        if rm.semantic_logits is not None:
            logits_v = rm.semantic_logits[ids].clone().requires_grad_(True)
        sup = [s for s in sup if len(s.pixels)]
        terms: dict[str, torch.Tensor] = {}
        if sup:
            # all batch pixels at once: rays, triangles relative to their camera, targets
            tri = np.concatenate([s.tri for s in sup])
            loc = self.lookup[tri]
            origins = np.concatenate([np.repeat(s.keyframe.T_world_camera[None, :3, 3], len(s.pixels), 0) for s in sup])
            rays = np.concatenate([world_rays(s.keyframe.T_world_camera, pixel_rays(s.camera)[s.pixels]) for s in sup])
            rel_xy = torch.from_numpy((rm.mesh.xy[tri] - origins[:, None, :2]).astype(np.float32))
            rel_z = z[loc] - torch.from_numpy(origins[:, 2:3].astype(np.float32))
            w, _ = ray_triangle_weights(torch.from_numpy(rays.astype(np.float32)),
                                        torch.cat([rel_xy, rel_z[..., None]], -1))
            colour_rows, offset, pos = [], 0, np.empty_like(loc)
            sample_cam = np.concatenate([[s.camera.name] * len(s.pixels) for s in sup])
            for cam_name in dict.fromkeys(s.camera.name for s in sup):
                mine = sample_cam == cam_name
                rows = np.arange(len(ids))
                colour_rows.append(rm.decoder.decode(codes[rows], cam_name))
                pos[mine] = offset + np.searchsorted(rows, loc[mine])
                offset += len(rows)
            rgb = (torch.cat(colour_rows)[pos] * w[..., None]).sum(1)
            target = np.concatenate([s.keyframe.image.reshape(-1, 3)[s.pixels] for s in sup])
            everywhere = torch.ones(len(rgb), dtype=torch.bool)
            terms["rgb"] = w_cfg.rgb * losses.colour_l1(rgb, torch.from_numpy(target).float() / 255, everywhere)
            if logits_v is not None:
                logits = (logits_v[loc] * w[..., None]).sum(1)
                labels = np.concatenate([s.keyframe.semantics.ravel()[s.pixels] for s in sup]).astype(np.int64)
                terms["semantics"] = w_cfg.semantics * losses.semantic_ce(logits, torch.from_numpy(labels), everywhere)
        if rm.elevation is not None:
            if len(lidar_ids):
                terms["elevation"] = w_cfg.elevation * losses.elevation_l1(
                    z[self.lookup[lidar_ids]], torch.from_numpy(lidar_z))
            terms["smoothness"] = w_cfg.smoothness * losses.smoothness(z, self._edges(ids))
        total = sum(terms.values())
        for opt in self.optimisers:
            opt.zero_grad(set_to_none=True)
        if isinstance(total, torch.Tensor) and total.requires_grad:
            total.backward()
        for opt in self.optimisers:
            opt.step()
        update = self.lookup[touched]
        rows = torch.from_numpy(ids[update])
        grad = codes.grad if codes.grad is not None else torch.zeros_like(codes)
        self.colour_opt.step(rows, grad[update])
        if self.semantic_opt is not None:
            g = logits_v.grad if logits_v.grad is not None else torch.zeros_like(logits_v)
            self.semantic_opt.step(rows, g[update])
        rm.z_now[ids] = z.detach().numpy()
        rm.observed[touched] += 1
        return {k: float(v.detach()) for k, v in terms.items()}

    def _edges(self, ids: np.ndarray) -> torch.Tensor:
        nb = self.map.mesh.neighbours[ids]
        nb_local = np.where(nb >= 0, self.lookup[np.maximum(nb, 0)], -1)
        own = np.broadcast_to(np.arange(len(ids))[:, None], nb.shape)
        keep = nb_local > own
        return torch.from_numpy(np.stack([own[keep], nb_local[keep]], 1))


def _batches(keyframes: list[Keyframe], trajectory: Trajectory, size: int) -> list[tuple[list[Keyframe], float]]:
    s = np.array([float(trajectory.along_track_at(k.timestamp)) for k in keyframes])
    order = np.argsort(s, kind="stable")
    out = []
    for lo in range(0, len(order), size):
        idx = order[lo : lo + size]
        out.append(([keyframes[i] for i in idx], float(np.mean(s[idx]))))
    return out


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


def _observe(road_map: RoadMap, train: list[Keyframe], cameras: dict[str, CameraModel], trajectory: Trajectory,
             fast: FastPathSettings, progress: bool, timings: dict[str, float]) -> VertexObservations:
    """Every keyframe's view of every vertex in reach; sets the vertices' observation counts and semantics."""
    started = time.perf_counter()
    mesh = road_map.mesh
    windows = WindowIndex.of(mesh)
    bar = tqdm(total=len(train), desc="observe", disable=not progress, unit="frame")

    def observe(keyframes: list[Keyframe]) -> VertexObservations:
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
        parts = list(pool.map(observe, [train[i::fast.threads_observe] for i in range(fast.threads_observe)]))
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


def _fit_colours(road_map: RoadMap, obs: VertexObservations, config: MapperConfig, fast: FastPathSettings,
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


def _waited_for(value, timings: dict[str, float], key: str):
    """An input that may still be in preparation (a Future: mapping.inputs.drive_inputs.LoadingDrive), once ready;
    the wait goes into `timings`."""
    if not isinstance(value, Future):
        return value
    started = time.perf_counter()
    ready = value.result()
    timings[key] = time.perf_counter() - started
    return ready


def reconstruct(
    keyframes: list[Keyframe] | Future[list[Keyframe]],
    cameras: dict[str, CameraModel],
    trajectory: Trajectory,
    lidar_ground_points: np.ndarray | None | Future[np.ndarray | None],
    config: MapperConfig,
    reference_height_m: float,
    out_dir: Path | None = None,
    ablation: str | None = None,
    gt: GroundTruth | None = None,
    faithful: bool = False,
    holdout_every: int = 10,
    fast: FastPathSettings = FastPathSettings(),
    progress: bool = True,
) -> ReconstructionResult:
    """Reconstruct the road surface seen by `keyframes` along `trajectory`; evaluate; export if out_dir.
    `keyframes` and `lidar_ground_points` may be Futures (inputs still loading): the mesh is built first,
    the Lidar waited for by the elevation fit, the keyframes after it."""
    start = time.perf_counter()
    torch.set_num_threads(config.threads if faithful else fast.threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    variant = variant_for(ablation)
    mesh = build_road_mesh(trajectory, config.corridor_half_width_m, config.mesh_side_m, reference_height_m,
                           flat=variant.flat_init)
    generator = torch.Generator().manual_seed(config.seed)
    road_map = new_road_map(
        mesh, variant, sorted(cameras), config.colour_code_dim, config.colour_mlp_layers, config.colour_mlp_width,
        config.positional_encoding_dim, config.elevation_mlp_layers, config.elevation_mlp_width,
        config.window_before_m + config.window_after_m, 0.0 if faithful else fast.elevation_lattice_m, generator,
    )
    history = []
    timings: dict[str, float] = {"setup_wall_s": time.perf_counter() - start}
    lidar_ground_points = _waited_for(lidar_ground_points, timings, "lidar_wait_s")
    supervision = lidar_ground_points if variant.lidar_supervision else None
    # the truth cells are placed on the mesh beside the Lidar points (numpy releases the GIL), which the
    # elevation fit, the Lidar detail and the metrics share
    side = ThreadPoolExecutor(1, thread_name_prefix="reconstruct-side")
    evaluation: PendingEvaluation | None = None
    try:
        truth_at = side.submit(Located.of, mesh, truth_cells(gt)[2]) if gt is not None else None
        have_lidar = lidar_ground_points is not None and len(lidar_ground_points) > 0
        lidar_at = Located.of(mesh, lidar_ground_points[:, :2]) if have_lidar else None
        if not faithful:  # the elevation needs the Lidar only: it is fitted while the images may still be decoding
            started = time.perf_counter()
            elevation_first_last = _fit_elevation(road_map, supervision, lidar_at, config, fast, rng)
            timings["elevation_fit_wall_s"] = time.perf_counter() - started
            if (road_map.elevation is not None and supervision is not None and len(supervision)
                    and fast.lidar_detail_passes):
                started = time.perf_counter()
                detail = fit_lidar_detail(road_map.z_now, lidar_at, supervision[:, 2],
                                          fast.lidar_detail_passes, fast.lidar_detail_prior)
                timings["lidar_detail_wall_s"] = time.perf_counter() - started
                timings["lidar_detail_mean_cm"] = 100.0 * float(np.abs(detail).mean())
        selected = select_keyframes(_waited_for(keyframes, timings, "keyframes_wait_s"), trajectory,
                                    config.keyframe_spacing_m)
        holdout = [k for i, k in enumerate(selected) if holdout_every > 0 and i % holdout_every == holdout_every // 2]
        held = {id(k) for k in holdout}
        train = [k for k in selected if id(k) not in held]
        if not train:
            raise ValueError("no training keyframes after selection")
        evaluation_args = (cameras, holdout, train, trajectory, lidar_ground_points, gt, config.window_before_m,
                           config.window_after_m)
        metric_points = MetricPoints(lidar_at, truth_at.result() if truth_at is not None else None)
        if faithful:
            lidar_ids, lidar_z = lidar_vertex_targets(mesh, supervision, lidar_at)
            opt = _Optimisation(road_map, cameras, config, lidar_ids, lidar_z)
            batches = _batches(train, trajectory, config.batch_size)
            with tqdm(total=config.epochs * len(batches), desc="emie-map", disable=not progress, unit="step") as bar:
                for _ in range(config.epochs):
                    road_map.refresh_elevation()
                    for b in rng.permutation(len(batches)):
                        terms = opt.step(*batches[b])
                        history.append(sum(terms.values()))
                        bar.set_postfix(loss=f"{history[-1]:.4f}")
                        bar.update()
            opt.colour_opt.flush()
            if opt.semantic_opt is not None:
                opt.semantic_opt.flush()
            road_map.refresh_elevation()
            evaluation = start_evaluation(road_map, *evaluation_args, metric_points)
        else:
            obs = _observe(road_map, train, cameras, trajectory, fast, progress, timings)
            # surface and semantics are final: the evaluation renders its views beside the colour fit
            evaluation = start_evaluation(road_map, *evaluation_args, metric_points)
            colour_first, colour_last = _fit_colours(road_map, obs, config, fast, rng, timings)
            w_rgb = config.loss_weights.rgb
            history = [elevation_first_last[0] + w_rgb * colour_first, elevation_first_last[1] + w_rgb * colour_last]
        train_s = time.perf_counter() - start
        drive_s = trajectory.duration_s
        # the export runs beside the evaluation's remaining work: both only read the finished map
        exported = side.submit(export_map, road_map, Path(out_dir), sorted(cameras)) if out_dir is not None else None
        side.shutdown(wait=False)
        metrics = finish_evaluation(evaluation)
        evaluate_s = time.perf_counter() - start - train_s
        files: dict[str, Path] = exported.result() if exported is not None else {}
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
        steps=len(history),
        vertices=mesh.num_vertices,
        vertices_observed=int((road_map.observed > 0).sum()),
        loss_first=history[0] if history else None,
        loss_last=float(np.mean(history[-max(1, len(history) // config.epochs) :])) if history else None,
        optimise_wall_s=train_s,
        evaluate_wall_s=evaluate_s,
        **timings,
        step_mean_s=(train_s - timings["setup_wall_s"]) / max(1, len(history)),
        drive_s=drive_s,
        realtime_factor=drive_s / train_s if train_s > 0 else None,
    )
    if out_dir is not None:
        path = Path(out_dir) / "metrics.json"
        path.write_text(json.dumps(metrics, indent=2))
        files["metrics"] = path
    return ReconstructionResult(metrics, road_map, files)

