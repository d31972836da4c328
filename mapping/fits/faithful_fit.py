"""The paper-faithful fit (EMIE-MAP as published): trajectory-based batches of adjacent keyframes, each step
the whole window (`windows.before_m` + `windows.after_m` around the batch) through the elevation MLP and the
colour decoders, every pixel of every batch image rasterised exactly against the full mesh, the four losses,
one Adam per parameter group (row-sparse Adam for the per-vertex colour codes and semantic logits)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from daemon.spine.mapper_config import MapperConfig
from daemon.spine.semantic_classes import NUM_MAP_CLASSES
from mapping.fits.lidar_occlusion import OcclusionTest
from mapping.localization.trajectory import HorizontalTrack
from mapping.method import losses
from mapping.method.mesh_location import Located
from mapping.method.mesh_renderer import pixel_rays, rasterise, ray_triangle_weights, world_rays
from mapping.method.road_map import RoadMap, WindowIndex
from mapping.method.road_mesh import RoadMesh
from mapping.method.row_sparse_adam import RowSparseAdam
from mapping.method.scene_data import CameraModel, Keyframe


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


class FaithfulOptimisation:
    """The paper-faithful optimisation: every pixel of every batch image rendered exactly against the
    whole 160 m window, every window vertex through the MLPs, each step."""

    def __init__(self, road_map, cameras, config, lidar_ids, lidar_z, occlusion: OcclusionTest | None = None):
        self.map, self.cameras, self.config = road_map, cameras, config
        self.occlusion = occlusion  # the views without semantics leave out the pixels it finds hidden
        self.maskless_reads = self.maskless_hidden = self.maskless_unchecked = 0
        self.windows = WindowIndex.of(road_map.mesh)
        self.lidar_ids, self.lidar_z = lidar_ids, lidar_z
        self.lidar_order = np.argsort(road_map.mesh.s[lidar_ids], kind="stable")
        self.lidar_s = road_map.mesh.s[lidar_ids][self.lidar_order]
        self.lookup = np.full(road_map.mesh.num_vertices, -1, np.int64)
        lr = config.faithful_fit.learning_rates
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
        seen = grid >= 0
        if kf.semantics is not None:  # a mask: its obstacle and unlabelled pixels are not used
            seen &= kf.semantics.ravel() < NUM_MAP_CLASSES
        pixels = np.nonzero(seen)[0]
        tri = tri_all[grid[pixels]]
        if kf.semantics is None:
            pixels, tri = self._unhidden(kf, cam, pixels, tri, vertices)
        return _Supervision(kf, cam, pixels, tri)

    def _unhidden(self, kf: Keyframe, cam: CameraModel, pixels: np.ndarray, tri: np.ndarray, vertices: np.ndarray):
        """The pixels of a view without semantics (and their triangles) the occlusion test does not find hidden
        (each at its triangle's first vertex: within 0.1 m of the point it sees)."""
        self.maskless_reads += len(pixels)
        if self.occlusion is None:
            return pixels, tri
        uv = np.stack([pixels % cam.width, pixels // cam.width], 1).astype(np.float64)
        hidden = self.occlusion.hidden(kf, cam, uv, vertices[tri[:, 0]])
        if hidden is None:
            self.maskless_unchecked += 1
            return pixels, tri
        self.maskless_hidden += int(hidden.sum())
        return pixels[~hidden], tri[~hidden]

    # -- one optimisation step ------------------------------------------------------------------
    def step(self, batch: list[Keyframe], s_center: float) -> dict[str, float]:
        cfg = self.config
        s_lo, s_hi = s_center - cfg.windows.before_m, s_center + cfg.windows.after_m
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
        rm, w_cfg = self.map, self.config.faithful_fit.loss_weights
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
            labelled = [s for s in sup if s.keyframe.semantics is not None]
            if logits_v is not None and labelled:  # over the pixels of the views with semantics only
                logits = (logits_v[loc] * w[..., None]).sum(1)
                labels = np.concatenate([s.keyframe.semantics.ravel()[s.pixels] if s.keyframe.semantics is not None
                                         else np.zeros(len(s.pixels), np.uint8) for s in sup]).astype(np.int64)
                with_labels = torch.from_numpy(np.concatenate([np.full(len(s.pixels), s.keyframe.semantics is not None)
                                                               for s in sup]))
                terms["semantics"] = w_cfg.semantics * losses.semantic_ce(logits, torch.from_numpy(labels), with_labels)
                rm.labelled[np.concatenate([s.tri.ravel() for s in labelled])] = True
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


def _batches(keyframes: list[Keyframe], trajectory: HorizontalTrack, size: int) -> list[tuple[list[Keyframe], float]]:
    s = np.array([float(trajectory.horizontal_distance_at(k.timestamp)) for k in keyframes])
    order = np.argsort(s, kind="stable")
    out = []
    for lo in range(0, len(order), size):
        idx = order[lo : lo + size]
        out.append(([keyframes[i] for i in idx], float(np.mean(s[idx]))))
    return out


def fit_faithful(road_map: RoadMap, cameras: dict[str, CameraModel], train: list[Keyframe], trajectory: HorizontalTrack,
                 supervision: np.ndarray | None, lidar_at: Located | None, config: MapperConfig,
                 rng: np.random.Generator, progress: bool,
                 occlusion: OcclusionTest | None = None) -> tuple[list[float], int, tuple[int, int, int]]:
    """Fit `road_map` to the training keyframes' pixels: `epochs` passes over the trajectory batches in a random
    order. The total loss of every step, the number of steps of the last epoch, and the views without
    semantics' pixel reads, those `occlusion` found hidden and the views it could not test (over all epochs)."""
    lidar_ids, lidar_z = lidar_vertex_targets(road_map.mesh, supervision, lidar_at)
    opt = FaithfulOptimisation(road_map, cameras, config, lidar_ids, lidar_z, occlusion)
    epochs = config.faithful_fit.epochs
    batches = _batches(train, trajectory, config.faithful_fit.batch_size)
    history: list[float] = []
    with tqdm(total=epochs * len(batches), desc="emie-map", disable=not progress, unit="step") as bar:
        for _ in range(epochs):
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
    return history, len(batches), (opt.maskless_reads, opt.maskless_hidden, opt.maskless_unchecked)
