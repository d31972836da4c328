"""The road map being reconstructed: mesh, per-vertex tables (colour codes, semantic logits), the
elevation residual MLP and the colour decoders, plus the variants the ablations switch between, and
exact rendering of the map into a camera view."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from daemon.spine.semantic_classes import NUM_MAP_CLASSES
from mapping.method.colour_mlps import ColourDecoder
from mapping.method.elevation_mlp import ElevationMLP
from mapping.method.mesh_renderer import pixel_rays, rasterise, ray_triangle_weights, sampled_pixels, world_rays
from mapping.method.road_mesh import RoadMesh, used_vertices
from mapping.method.scene_data import CameraModel, Keyframe

CODE_INIT_STD = 0.1
SEMANTIC_INIT_STD = 0.1
NO_LABEL = 255
DECODE_CHUNK = 262_144  # vertices per batch when the whole mesh goes through the models


@dataclass(frozen=True)
class Variant:
    """Which parts of EMIE-MAP are on (the ablations turn them off)."""

    elevation_mlp: bool = True  # learn a residual over z0; False keeps z = z0
    colour: str = "mlps"  # "mlps" (per-camera decoders), "embedding" (one decoder + camera embedding), "explicit"
    semantics: bool = True
    flat_init: bool = False  # RoMe: z0 is one flat height, the MLP gives the whole (absolute) relief
    lidar_supervision: bool = True  # False: RoMe is camera-only (Lidar points still measure Elev-error)


ABLATIONS: dict[str, Variant] = {
    "no-elevation-mlp": Variant(elevation_mlp=False),
    "no-colour-mlps": Variant(colour="explicit"),
    "embedding": Variant(colour="embedding"),
    "no-semantics": Variant(semantics=False),
    "rome": Variant(colour="explicit", flat_init=True, lidar_supervision=False),
}


def variant_for(ablation: str | None) -> Variant:
    if ablation is None:
        return Variant()
    if ablation not in ABLATIONS:
        raise ValueError(f"unknown ablation {ablation!r}; choose from {sorted(ABLATIONS)}")
    return ABLATIONS[ablation]


@dataclass
class RoadMap:
    mesh: RoadMesh
    variant: Variant
    elevation: ElevationMLP | None
    decoder: ColourDecoder
    colour_params: torch.Tensor  # (N, D) colour codes, or explicit RGB logits
    semantic_logits: torch.Tensor | None  # (N, NUM_MAP_CLASSES)
    lattice_m: float  # > 0: the residual MLP is evaluated on a square lattice this coarse
    z_now: np.ndarray  # (N,) float32 latest elevation of every vertex (no gradient)
    observed: np.ndarray  # (N,) int32 how many training steps supervised each vertex through a pixel
    labelled: np.ndarray  # (N,) bool: a view with semantics (a mask or a model's labels) trained the vertex's
    # logits; the others' labels are NO_LABEL wherever the map is read (a view without semantics gives none)

    def elevation_of(self, ids: np.ndarray) -> torch.Tensor:
        """Elevation of vertices `ids`, differentiable w.r.t. the elevation MLP."""
        z0 = torch.from_numpy(self.mesh.z0[ids])
        if self.elevation is None:
            return z0
        return z0 + self.elevation.residual(self.mesh.xy[ids], self.lattice_m)

    @torch.no_grad()
    def refresh_elevation(self) -> None:
        for lo in range(0, self.mesh.num_vertices, DECODE_CHUNK):
            ids = np.arange(lo, min(lo + DECODE_CHUNK, self.mesh.num_vertices))
            self.z_now[ids] = self.elevation_of(ids).numpy()

    @torch.no_grad()
    def vertex_colours(self, camera: str, ids: np.ndarray | None = None) -> np.ndarray:
        ids = np.arange(self.mesh.num_vertices) if ids is None else ids
        out = np.empty((len(ids), 3), np.float32)
        for lo in range(0, len(ids), DECODE_CHUNK):
            part = ids[lo : lo + DECODE_CHUNK]
            out[lo : lo + len(part)] = self.decoder.decode(self.colour_params[part], camera).numpy()
        return out

    def state_dict(self) -> dict:
        state = {
            "variant": self.variant.__dict__,
            "lattice_m": self.lattice_m,
            "mesh_side_m": self.mesh.side_m,
            "mesh_origin": self.mesh.origin,
            "vertex_rc": torch.from_numpy(self.mesh.rc),
            "z0": torch.from_numpy(self.mesh.z0),
            "z": torch.from_numpy(self.z_now),
            "observed": torch.from_numpy(self.observed),
            "colour_params": self.colour_params,
            "decoder": self.decoder.state_dict(),
        }
        if self.elevation is not None:
            state["elevation_mlp"] = self.elevation.state_dict()
        if self.semantic_logits is not None:
            state["semantic_logits"] = self.semantic_logits
            state["labelled"] = torch.from_numpy(self.labelled)
        return state

    @torch.no_grad()
    def labels_at(self, ids: np.ndarray, weights: torch.Tensor) -> np.ndarray:
        """(M,) uint8 class ids where the map is read through triangles `ids` (M, 3) with barycentric `weights`
        (M, 3): the argmax of the interpolated logits, NO_LABEL where a vertex is not labelled or the map has
        no semantics."""
        out = np.full(len(ids), NO_LABEL, np.uint8)
        if self.semantic_logits is not None and len(ids):
            logits = (self.semantic_logits[ids] * weights.to(self.semantic_logits.dtype)[..., None]).sum(1)
            out[:] = np.where(self.labelled[ids].all(1), logits.argmax(1).numpy(), NO_LABEL)
        return out


def new_road_map(
    mesh: RoadMesh,
    variant: Variant,
    camera_names: list[str],
    code_dim: int,
    colour_layers: int,
    colour_width: int,
    encoding_dim: int,
    elevation_layers: int,
    elevation_width: int,
    encoding_scale_m: float,
    lattice_m: float,
    generator: torch.Generator,
) -> RoadMap:
    decoder = ColourDecoder(variant.colour, camera_names, code_dim, colour_layers, colour_width)
    n = mesh.num_vertices
    if variant.colour == "explicit":
        colour = torch.zeros(n, 3)
    else:
        colour = torch.randn(n, code_dim, generator=generator) * CODE_INIT_STD
    semantics = torch.randn(n, NUM_MAP_CLASSES, generator=generator) * SEMANTIC_INIT_STD if variant.semantics else None
    elevation = None
    if variant.elevation_mlp:
        origin = (float(mesh.xy[:, 0].mean()), float(mesh.xy[:, 1].mean()))
        elevation = ElevationMLP(origin, encoding_dim, elevation_layers, elevation_width, encoding_scale_m)
    return RoadMap(mesh, variant, elevation, decoder, colour, semantics, lattice_m, mesh.z0.copy(),
                   np.zeros(n, np.int32), np.zeros(n, bool))


@dataclass(frozen=True)
class WindowIndex:
    """Vertices and faces ordered by along-track position, to cut the paper's windows in O(log N)."""

    vertex_order: np.ndarray
    vertex_s: np.ndarray
    face_order: np.ndarray
    face_s: np.ndarray

    @staticmethod
    def of(mesh: RoadMesh) -> WindowIndex:
        vo = np.argsort(mesh.s, kind="stable")
        fs = mesh.s[mesh.faces].mean(1)
        fo = np.argsort(fs, kind="stable")
        return WindowIndex(vo, mesh.s[vo], fo, fs[fo])

    def vertices(self, s_lo: float, s_hi: float) -> np.ndarray:
        a, b = np.searchsorted(self.vertex_s, [s_lo, s_hi])
        return np.sort(self.vertex_order[a:b])

    def faces(self, s_lo: float, s_hi: float) -> np.ndarray:
        a, b = np.searchsorted(self.face_s, [s_lo, s_hi])
        return self.face_order[a:b]


@dataclass(frozen=True)
class ViewGeometry:
    """What a camera sees of the mesh at every `stride`-th pixel (an exact, z-buffered render): it depends on
    the surface only, so colours can still be fitting while it is made."""

    shape: tuple[int, int]  # (H', W') of the sampled pixels (mesh_renderer.sampled_pixels)
    hit: np.ndarray  # (H' * W',) bool: the pixel sees the mesh
    tri: np.ndarray  # (P, 3) vertex ids of the triangle each hit pixel sees
    weights: torch.Tensor  # (P, 3) barycentric weights where the pixel's ray crosses it


@torch.no_grad()
def view_geometry(road_map: RoadMap, faces: np.ndarray, keyframe: Keyframe, camera: CameraModel,
                  stride: int = 1) -> ViewGeometry:
    """The mesh faces `faces` (indices into mesh.faces) as `camera` at `keyframe` sees them."""
    mesh = road_map.mesh
    tri_all = mesh.faces[faces]
    used, local = used_vertices(tri_all, mesh.num_vertices)  # only the vertices these faces use
    vertices = np.concatenate([mesh.xy[used], road_map.z_now[used, None].astype(np.float64)], 1)
    face_grid = rasterise(vertices, local.reshape(-1, 3), camera, keyframe.T_world_camera, stride).ravel()
    hit = face_grid >= 0
    sampled = sampled_pixels(camera, stride)
    tri = tri_all[face_grid[hit]]
    w = pixel_weights(road_map, keyframe, camera, sampled.ravel()[hit], tri, torch.from_numpy(road_map.z_now[tri]))
    return ViewGeometry(sampled.shape, hit, tri, w)


@torch.no_grad()
def view_labels(road_map: RoadMap, view: ViewGeometry) -> np.ndarray:
    """(H', W') uint8 rendered class ids, NO_LABEL where the mesh is not seen or the map has no semantics there."""
    labels = np.full(view.hit.size, NO_LABEL, np.uint8)
    labels[view.hit] = road_map.labels_at(view.tri, view.weights)
    return labels.reshape(view.shape)


@torch.no_grad()
def view_rgb(road_map: RoadMap, view: ViewGeometry, camera: str) -> np.ndarray:
    """(H', W', 3) float32 rendered colours in [0, 1] as `camera`'s decoder gives them (0 where not seen)."""
    ids, inverse = used_vertices(view.tri, road_map.mesh.num_vertices)
    rgb = np.zeros((view.hit.size, 3), np.float32)
    colours = torch.from_numpy(road_map.vertex_colours(camera, ids))
    rgb[view.hit] = (colours[inverse] * view.weights[..., None]).sum(1).clamp(0, 1).numpy()
    return rgb.reshape(*view.shape, 3)


def pixel_weights(
    road_map: RoadMap,
    keyframe: Keyframe,
    camera: CameraModel,
    pixels: np.ndarray,
    tri: np.ndarray,
    tri_z: torch.Tensor,
) -> torch.Tensor:
    """Barycentric weights (P, 3) where the pixels' rays cross their triangles (vertex ids `tri`,
    elevations `tri_z` (P, 3), differentiable)."""
    origin = keyframe.T_world_camera[:3, 3]
    rays = world_rays(keyframe.T_world_camera, pixel_rays(camera)[pixels])
    rel_xy = torch.from_numpy(road_map.mesh.xy[tri] - origin[:2]).to(tri_z.dtype)
    tri_rel = torch.cat([rel_xy, (tri_z - float(origin[2]))[..., None]], -1)
    w, _ = ray_triangle_weights(torch.from_numpy(rays).to(tri_z.dtype), tri_rel)
    return w
