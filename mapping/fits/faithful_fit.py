"""The paper-faithful fit (EMIE-MAP as published): trajectory-based batches of adjacent keyframes, each step
the whole window (`windows.before_m` + `windows.after_m` around the batch) through the elevation MLP and the
colour decoders, every pixel of every batch image rasterised exactly against the full mesh, the four losses,
one Adam per parameter group (row-sparse Adam for the per-vertex colour codes and semantic logits). On
`mapper.device`: the mesh, the keyframes and the model move there once before the loop, and a step copies nothing
between host and device (the windows are cut by index on the host; the losses are read back once an epoch)."""

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
from mapping.method.adam import Adam
from mapping.method.compute_device import optimisation_loop, resolve_device
from mapping.method.mesh_location import Located
from mapping.method.mesh_renderer import pixel_rays, rasterise_tensors, ray_triangle_weights, world_rays_tensors
from mapping.method.road_map import DECODE_CHUNK, RoadMap, WindowIndex
from mapping.method.road_mesh import RoadMesh
from mapping.method.row_sparse_adam import RowSparseAdam
from mapping.method.scene_data import CameraModel, Keyframe

_CPU = torch.device("cpu")  # where the road map lives before and after the fit


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
class _View:
    """A training keyframe on the fit's device, moved once before the loop: its pose, image and semantics."""

    T_world_camera: torch.Tensor  # (4, 4) float64
    image: torch.Tensor  # (H * W, 3) uint8
    semantics: torch.Tensor | None  # (H * W,) uint8, None: no semantics
    occluders: torch.Tensor | None = None  # without semantics: the occlusion test's nearest standing depth per
    # image cell (OcclusionTest.nearest_depths, float64); None: no test, or no Lidar scan near enough in time


@dataclass
class _Supervision:
    """One keyframe's pixels used in a step and the triangles they see (tensors on the fit's device)."""

    keyframe: Keyframe
    camera: CameraModel
    view: _View
    pixels: torch.Tensor  # (P,) flat pixel indices
    tri: torch.Tensor  # (P, 3) vertex ids


@dataclass
class _WindowMesh:
    """The faces of one step's window, and the vertices they use, on the fit's device."""

    tri_all: torch.Tensor  # (F, 3) vertex ids of the window's faces
    vertices: torch.Tensor  # (U, 3) float64 world positions of the vertices they use (z: the latest elevation)
    local: torch.Tensor  # (F, 3) the faces as indices into `vertices`


class FaithfulOptimisation:
    """The paper-faithful optimisation: every pixel of every batch image rendered exactly against the
    whole 160 m window, every window vertex through the MLPs, each step. The model, the mesh, the training
    keyframes and the per-vertex state the steps change (latest elevation, observation counts, labelled) live on
    `device` from construction; `finish` brings them back to the road map (on the CPU)."""

    def __init__(self, road_map, cameras, config, lidar_ids, lidar_z, occlusion: OcclusionTest | None = None,
                 keyframes: list[Keyframe] = (), device: torch.device = _CPU):
        self.map, self.cameras, self.config, self.device = road_map, cameras, config, device
        self.occlusion = occlusion  # the views without semantics leave out the pixels it finds hidden
        self.maskless_reads = self.maskless_hidden = self.maskless_unchecked = 0
        mesh = road_map.mesh
        windows = WindowIndex.of(mesh)
        self.vertex_s, self.face_s = windows.vertex_s, windows.face_s  # host: the windows are cut by s on the host
        lidar_order = np.argsort(mesh.s[lidar_ids], kind="stable")
        self.lidar_s = mesh.s[lidar_ids][lidar_order]

        def put(array: np.ndarray, dtype: torch.dtype | None = None) -> torch.Tensor:
            array = np.ascontiguousarray(array)
            return torch.from_numpy(array if array.flags.writeable else array.copy()).to(device, dtype)

        self.vertex_order = put(windows.vertex_order, torch.int64)
        self.face_order = put(windows.face_order, torch.int64)
        self.lidar_order, self.lidar_ids, self.lidar_z = (put(lidar_order, torch.int64), put(lidar_ids, torch.int64),
                                                          put(lidar_z))
        self.xy, self.z0, self.faces = put(mesh.xy, torch.float64), put(mesh.z0), put(mesh.faces, torch.int64)
        self.neighbours = put(mesh.neighbours, torch.int64)
        self.z_now, self.observed, self.labelled = put(road_map.z_now), put(road_map.observed), put(road_map.labelled)
        self.lookup = torch.full((mesh.num_vertices,), -1, dtype=torch.int64, device=device)
        self.rays = {name: put(pixel_rays(cam)) for name, cam in cameras.items()}
        self.views = {id(kf): _View(put(kf.T_world_camera, torch.float64), put(kf.image.reshape(-1, 3)),
                                    None if kf.semantics is None else put(kf.semantics.reshape(-1)))
                      for kf in keyframes}
        self._hidden_count = torch.zeros((), dtype=torch.int64, device=device)
        self._untested: set[int] = set()  # views without semantics the occlusion test cannot test
        for kf in keyframes:  # what hides the road in a view depends on the view only: found once, on the host
            if kf.semantics is None and occlusion is not None:
                nearest = occlusion.nearest_depths(kf, cameras[kf.camera])
                if nearest is None:
                    self._untested.add(id(kf))
                else:
                    self.views[id(kf)].occluders = put(nearest, torch.float64)
        self.origin = None
        if road_map.elevation is not None:
            road_map.elevation.to(device)
            self.origin = torch.tensor(road_map.elevation.origin_xy, dtype=torch.float64, device=device)
        road_map.decoder.to(device)
        road_map.colour_params = road_map.colour_params.to(device)
        if road_map.semantic_logits is not None:
            road_map.semantic_logits = road_map.semantic_logits.to(device)
        lr = config.faithful_fit.learning_rates
        self.optimisers = []
        if road_map.elevation is not None:
            self.optimisers.append(Adam([(road_map.elevation.parameters(), lr.elevation_mlp)]))
        decoder_params = list(road_map.decoder.parameters())
        if decoder_params:
            self.optimisers.append(Adam([(decoder_params, lr.colour_mlps)]))
        self.colour_opt = RowSparseAdam(road_map.colour_params, lr=lr.colour_codes)
        self.semantic_opt = None
        if road_map.semantic_logits is not None:
            self.semantic_opt = RowSparseAdam(road_map.semantic_logits, lr=lr.semantics)

    def elevation_of(self, ids: torch.Tensor) -> torch.Tensor:
        """RoadMap.elevation_of on the device: vertices `ids`, differentiable w.r.t. the elevation MLP."""
        z0 = self.z0[ids]
        if self.map.elevation is None:
            return z0
        local = (self.xy[ids] - self.origin).to(torch.float32)
        return z0 + self.map.elevation.residual_at(local, self.map.lattice_m)

    @torch.no_grad()
    def refresh_elevation(self) -> None:
        """RoadMap.refresh_elevation into the device's latest elevation (the same chunks, the same sums)."""
        n = len(self.z_now)
        for lo in range(0, n, DECODE_CHUNK):
            ids = torch.arange(lo, min(lo + DECODE_CHUNK, n), device=self.device)
            self.z_now[ids] = self.elevation_of(ids)

    def finish(self) -> None:
        """Settle the row-sparse optimisers and bring the model and the per-vertex state back to the road map."""
        self.colour_opt.flush()
        if self.semantic_opt is not None:
            self.semantic_opt.flush()
        rm = self.map
        rm.colour_params = rm.colour_params.to(_CPU)
        if rm.semantic_logits is not None:
            rm.semantic_logits = rm.semantic_logits.to(_CPU)
        if rm.elevation is not None:
            rm.elevation.to(_CPU)
        rm.decoder.to(_CPU)
        self.maskless_hidden += int(self._hidden_count)
        self._hidden_count.zero_()
        rm.z_now[:] = self.z_now.cpu().numpy()
        rm.observed[:] = self.observed.cpu().numpy()
        rm.labelled[:] = self.labelled.cpu().numpy()

    # -- what each pixel sees -------------------------------------------------------------------
    def window_mesh(self, faces: torch.Tensor) -> _WindowMesh:
        tri_all = self.faces[faces]
        used, local = torch.unique(tri_all, return_inverse=True)  # project only the vertices these faces use
        vertices = torch.cat([self.xy[used], self.z_now[used, None].to(torch.float64)], 1)
        return _WindowMesh(tri_all, vertices, local)

    def exact_supervision(self, kf: Keyframe, window: _WindowMesh) -> _Supervision:
        cam, view = self.cameras[kf.camera], self.views[id(kf)]
        grid = rasterise_tensors(window.vertices, window.local, cam, view.T_world_camera, max_candidates=None)
        seen = grid >= 0
        if view.semantics is not None:  # a mask: its obstacle and unlabelled pixels are not used
            seen &= view.semantics < NUM_MAP_CLASSES
        pixels = torch.nonzero(seen)[:, 0]
        tri = window.tri_all[grid[pixels]]
        if kf.semantics is None:
            pixels, tri = self._unhidden(kf, cam, pixels, tri)
        return _Supervision(kf, cam, view, pixels, tri)

    def _unhidden(self, kf: Keyframe, cam: CameraModel, pixels: torch.Tensor, tri: torch.Tensor):
        """The pixels of a view without semantics (and their triangles) the occlusion test does not find hidden
        (each at its triangle's first vertex: within 0.1 m of the point it sees): OcclusionTest.hidden on the
        device, against the view's standing depths found before the loop; the hidden count is read after it."""
        self.maskless_reads += len(pixels)
        if self.occlusion is None:
            return pixels, tri
        occluders = self.views[id(kf)].occluders
        if occluders is None:
            self.maskless_unchecked += id(kf) in self._untested
            return pixels, tri
        cell, T = self.occlusion.settings.cell_px, self.views[id(kf)].T_world_camera
        first = tri[:, 0]
        points = torch.cat([self.xy[first], self.z_now[first, None].to(torch.float64)], 1)
        d = points - T[:3, 3]
        depth = d[:, 0] * T[0, 2] + d[:, 1] * T[1, 2] + d[:, 2] * T[2, 2]  # lidar_occlusion._depth
        behind = occluders[torch.div(pixels, cam.width, rounding_mode="floor") // cell, (pixels % cam.width) // cell]
        hidden = behind < depth - self.occlusion.settings.margin_m
        self._hidden_count += hidden.sum()
        keep = ~hidden
        return pixels[keep], tri[keep]

    # -- one optimisation step ------------------------------------------------------------------
    def step(self, batch: list[Keyframe], s_center: float) -> list[torch.Tensor]:
        """One step on `batch` around `s_center`; its loss terms (detached, on the device: read after the loop)."""
        cfg = self.config
        s_lo, s_hi = s_center - cfg.windows.before_m, s_center + cfg.windows.after_m
        a, b = np.searchsorted(self.face_s, [s_lo, s_hi])
        faces = self.face_order[a:b]
        a, b = np.searchsorted(self.lidar_s, [s_lo, s_hi])
        lidar_sel = self.lidar_order[a:b]
        # the window's vertices, and every vertex of its faces and of its Lidar points (a face near the window's
        # edge has vertices just outside it): each is looked up in the window, none reads another's row
        a, b = np.searchsorted(self.vertex_s, [s_lo, s_hi])
        window = torch.unique(torch.cat([self.vertex_order[a:b], self.faces[faces].reshape(-1),
                                         self.lidar_ids[lidar_sel]]))
        z = self.elevation_of(window)
        self.z_now[window] = z.detach()  # the views are rasterised on the current surface
        mesh = self.window_mesh(faces)
        sup = [self.exact_supervision(kf, mesh) for kf in batch]
        touched = torch.unique(torch.cat([s.tri.reshape(-1) for s in sup]))
        self.lookup[window] = torch.arange(len(window), device=self.device)
        try:
            result = self._losses(sup, window, touched, self.lidar_ids[lidar_sel], self.lidar_z[lidar_sel], z)
        finally:
            self.lookup[window] = -1
        return result

    def _losses(self, sup, ids, touched, lidar_ids, lidar_z, z) -> list[torch.Tensor]:
        rm, w_cfg, device = self.map, self.config.faithful_fit.loss_weights, self.device
        codes = rm.colour_params[ids].clone().requires_grad_(True)
        logits_v = None
        if rm.semantic_logits is not None:
            logits_v = rm.semantic_logits[ids].clone().requires_grad_(True)
        sup = [s for s in sup if len(s.pixels)]
        terms: dict[str, torch.Tensor] = {}
        if sup:
            # all batch pixels at once: rays, triangles relative to their camera, targets
            tri = torch.cat([s.tri for s in sup])
            loc = self.lookup[tri]
            origins = torch.cat([s.view.T_world_camera[None, :3, 3].expand(len(s.pixels), 3) for s in sup])
            rays = torch.cat([world_rays_tensors(s.view.T_world_camera, self.rays[s.camera.name][s.pixels])
                              for s in sup])
            rel_xy = (self.xy[tri] - origins[:, None, :2]).to(torch.float32)
            rel_z = z[loc] - origins[:, 2:3].to(torch.float32)
            w, _ = ray_triangle_weights(rays.to(torch.float32), torch.cat([rel_xy, rel_z[..., None]], -1))
            # each camera's decoder over every window vertex, one block per camera; a pixel reads its camera's
            # block at its vertices
            names = list(dict.fromkeys(s.camera.name for s in sup))
            colour_rows = torch.cat([rm.decoder.decode(codes, name) for name in names])
            block = torch.cat([torch.full((len(s.pixels),), names.index(s.camera.name) * len(ids), device=device)
                               for s in sup])
            rgb = (colour_rows[block[:, None] + loc] * w[..., None]).sum(1)
            target = torch.cat([s.view.image[s.pixels] for s in sup])
            everywhere = torch.ones(len(rgb), dtype=torch.bool, device=device)
            terms["rgb"] = w_cfg.rgb * losses.colour_l1(rgb, target.float() / 255, everywhere)
            labelled = [s for s in sup if s.view.semantics is not None]
            if logits_v is not None and labelled:  # over the pixels of the views with semantics only
                logits = (logits_v[loc] * w[..., None]).sum(1)
                labels = torch.cat([s.view.semantics[s.pixels] if s.view.semantics is not None
                                    else torch.zeros(len(s.pixels), dtype=torch.uint8, device=device)
                                    for s in sup]).to(torch.int64)
                with_labels = torch.cat([torch.full((len(s.pixels),), s.view.semantics is not None, device=device)
                                         for s in sup])
                terms["semantics"] = w_cfg.semantics * losses.semantic_ce(logits, labels, with_labels)
                self.labelled[torch.cat([s.tri.reshape(-1) for s in labelled])] = True
        if rm.elevation is not None:
            if len(lidar_ids):
                terms["elevation"] = w_cfg.elevation * losses.elevation_l1(z[self.lookup[lidar_ids]], lidar_z)
            terms["smoothness"] = w_cfg.smoothness * losses.smoothness(z, self._edges(ids))
        total = sum(terms.values())
        for opt in self.optimisers:
            opt.zero_grad()
        if isinstance(total, torch.Tensor) and total.requires_grad:
            total.backward()
        for opt in self.optimisers:
            opt.step()
        update = self.lookup[touched]
        rows = ids[update]
        grad = codes.grad if codes.grad is not None else torch.zeros_like(codes)
        self.colour_opt.step(rows, grad[update])
        if self.semantic_opt is not None:
            g = logits_v.grad if logits_v.grad is not None else torch.zeros_like(logits_v)
            self.semantic_opt.step(rows, g[update])
        self.z_now[ids] = z.detach()
        self.observed[touched] += 1
        return [v.detach() for v in terms.values()]

    def _edges(self, ids: torch.Tensor) -> torch.Tensor:
        nb = self.neighbours[ids]
        nb_local = torch.where(nb >= 0, self.lookup[nb.clamp(min=0)], -1)
        own = torch.arange(len(ids), device=self.device)[:, None].expand(nb.shape)
        keep = nb_local > own
        return torch.stack([own[keep], nb_local[keep]], 1)


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
    order, on `config.device` (the model and the keyframes moved there once; the losses read back once an epoch).
    The total loss of every step, the number of steps of the last epoch, and the views without
    semantics' pixel reads, those `occlusion` found hidden and the views it could not test (over all epochs)."""
    lidar_ids, lidar_z = lidar_vertex_targets(road_map.mesh, supervision, lidar_at)
    opt = FaithfulOptimisation(road_map, cameras, config, lidar_ids, lidar_z, occlusion, train,
                               resolve_device(config.device))
    epochs = config.faithful_fit.epochs
    batches = _batches(train, trajectory, config.faithful_fit.batch_size)
    history: list[float] = []
    with tqdm(total=epochs * len(batches), desc="emie-map", disable=not progress, unit="step") as bar:
        for _ in range(epochs):
            opt.refresh_elevation()
            steps = []
            with optimisation_loop("faithful"):
                for b in rng.permutation(len(batches)):
                    steps.append(opt.step(*batches[b]))
                    bar.update()
            history += _step_totals(steps)
            if history:
                bar.set_postfix(loss=f"{history[-1]:.4f}")
    opt.finish()
    road_map.refresh_elevation()
    return history, len(batches), (opt.maskless_reads, opt.maskless_hidden, opt.maskless_unchecked)


def _step_totals(steps: list[list[torch.Tensor]]) -> list[float]:
    """Each step's total loss from its terms (on the device), read back at once; summed on the host in the
    terms' order, as floats (what the loss history has always held)."""
    flat = [term for terms in steps for term in terms]
    values = torch.stack(flat).tolist() if flat else []
    totals, at = [], 0
    for terms in steps:
        totals.append(sum(values[at : at + len(terms)]))
        at += len(terms)
    return totals
