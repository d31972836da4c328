"""Writing a reconstructed road map to disk: BEV rasters (RGB per camera, semantics, elevation as PNG, GeoTIFF and
raw .npy, bev.json with their origin, resolution and CRS), the mesh with vertex colours and labels (PLY, GLB:
mesh_files) and a state_dict checkpoint. A map without semantics (no masks and no model) has no semantic files and
no labels."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh

from daemon.spine.local_frame import LocalFrame
from mapping.method.road_map import NO_LABEL, RoadMap
from mapping.method.road_mesh import used_vertices
from mapping.outputs import map_geotiff
from mapping.outputs.map_annotation import annotated_map
from mapping.outputs.map_colours import elevation_image, elevation_range, semantic_image
from mapping.outputs.map_metrics import observed_triangles
from mapping.outputs.mesh_files import write_mesh_files

_ROWS_PER_CHUNK = 256


def vertex_labels(road_map: RoadMap) -> np.ndarray:
    """(N,) uint8 class id of every vertex, NO_LABEL where it is not labelled (RoadMap.labelled)."""
    if road_map.semantic_logits is None:
        return np.full(road_map.mesh.num_vertices, NO_LABEL, np.uint8)
    return np.where(road_map.labelled, road_map.semantic_logits.argmax(1).numpy(), NO_LABEL).astype(np.uint8)


def bev_rasters(road_map: RoadMap, cameras: list[str], resolution_m: float, threads: int,
                confidence: bool = False) -> dict:
    """Rasters over the observed area; cell (i, j) is centred at (x0 + j*res, y0 + i*res). Blocks of rows are
    filled on `threads` threads (numpy and torch release the GIL in the blocks' array work). `confidence` adds
    what a fusion of maps weighs them by: `weight` (H, W) float32, log(1 + the training steps that supervised the
    cell's vertices), 0 where unobserved, and `class_prob` (H, W, classes) float32, the softmax of the interpolated
    semantic logits where the cell is labelled, 0 elsewhere (None when the map has no semantics)."""
    seen = road_map.observed > 0
    xy = road_map.mesh.xy[seen] if seen.any() else road_map.mesh.xy
    lo, hi = np.floor(xy.min(0) / resolution_m) * resolution_m, xy.max(0)
    w, h = (np.ceil((hi - lo) / resolution_m).astype(int) + 1).tolist()
    colours = {c: road_map.vertex_colours(c) for c in cameras}
    elevation = np.full((h, w), np.nan, np.float32)
    labels = np.full((h, w), NO_LABEL, np.uint8)
    rgb = {c: np.zeros((h, w, 3), np.uint8) for c in cameras}
    semantics = road_map.semantic_logits is not None
    weight = np.zeros((h, w), np.float32) if confidence else None
    class_prob = (np.zeros((h, w, road_map.semantic_logits.shape[1]), np.float32)
                  if confidence and semantics else None)
    support = np.log1p(road_map.observed.astype(np.float32))

    def fill(r0: int) -> None:  # one block of rows: the blocks write disjoint rows
        rows = np.arange(r0, min(h, r0 + _ROWS_PER_CHUNK))
        jj, ii = np.meshgrid(np.arange(w), rows)
        pts = np.stack([lo[0] + jj.ravel() * resolution_m, lo[1] + ii.ravel() * resolution_m], 1)
        ids, wt, ok = observed_triangles(road_map, pts)
        ids, wt = ids[ok], wt[ok]
        flat = (ii.ravel()[ok], jj.ravel()[ok])
        elevation[flat] = (road_map.z_now[ids] * wt).sum(1)
        labels[flat] = road_map.labels_at(ids, torch.from_numpy(wt).float())
        for c in cameras:
            rgb[c][flat] = np.clip((colours[c][ids] * wt[..., None]).sum(1) * 255 + 0.5, 0, 255).astype(np.uint8)
        if weight is not None:
            weight[flat] = (support[ids] * wt).sum(1)
        if class_prob is not None:
            logits = (road_map.semantic_logits[ids] * torch.from_numpy(wt).to(road_map.semantic_logits.dtype)[..., None]
                      ).sum(1)
            prob = torch.softmax(logits.float(), 1).numpy()
            class_prob[flat] = np.where(road_map.labelled[ids].all(1)[:, None], prob, 0.0)

    with ThreadPoolExecutor(threads, thread_name_prefix="export-raster") as pool:
        list(pool.map(fill, range(0, h, _ROWS_PER_CHUNK)))
    out = {"origin_xy": (float(lo[0]), float(lo[1])), "elevation": elevation, "labels": labels, "rgb": rgb}
    return out | ({"weight": weight, "class_prob": class_prob} if confidence else {})


def export_map(road_map: RoadMap, out_dir: Path, cameras: list[str], raster_threads: int,
               origin: LocalFrame | None = None) -> dict[str, Path]:
    """The map's files in `out_dir`. `origin`: the geodetic origin of the map's ENU frame (None: unknown, the
    GeoTIFFs have no CRS and bev.json no origin)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(1, thread_name_prefix="export-mesh") as pool:  # the mesh beside the rasters
        mesh_files = pool.submit(_export_mesh, road_map, out_dir, cameras[0],
                                 [origin.lat_deg, origin.lon_deg, origin.alt_m] if origin is not None else None)
        return _export_rasters(road_map, out_dir, cameras, raster_threads, origin) | mesh_files.result()


def _export_rasters(road_map: RoadMap, out_dir: Path, cameras: list[str], raster_threads: int,
                    origin: LocalFrame | None) -> dict[str, Path]:
    """The bird's-eye rasters: RGB per camera, semantics and elevation as PNGs and GeoTIFFs, the grids as .npy,
    bev.json."""
    res = road_map.mesh.side_m
    bev = bev_rasters(road_map, cameras, res, raster_threads)
    files: dict[str, Path] = {}

    def save_png(name: str, rgb: np.ndarray, **annotation) -> None:
        """`name`.png, one pixel per cell, and `name`_annotated.png with its legend or colour bar, scale, north."""
        for file, image in ((f"{name}.png", np.flipud(rgb)),
                            (f"{name}_annotated.png", annotated_map(rgb, res, **annotation))):
            cv2.imwrite(str(out_dir / file), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))  # north up
            files[file] = out_dir / file

    semantics = road_map.semantic_logits is not None  # without: no semantic files (not a raster of NO_LABEL)
    for c in cameras:
        save_png(f"bev_rgb_{c}", bev["rgb"][c], title=f"colour: {c}")
    if semantics:
        save_png("bev_semantics", semantic_image(bev["labels"]), title="semantics", legend=True)
    save_png("bev_elevation", elevation_image(bev["elevation"]), title="elevation",
             elevation_range_m=elevation_range(bev["elevation"]))
    arrays = [("bev_elevation.npy", bev["elevation"])] + ([("bev_semantics.npy", bev["labels"])] if semantics else [])
    for name, array in arrays:
        np.save(out_dir / name, array)
        files[name] = out_dir / name
    crs = map_geotiff.local_crs(origin) if origin is not None else None
    grid = (bev["origin_xy"], res)
    tifs = {"bev_elevation.tif": lambda p: map_geotiff.write_elevation(p, bev["elevation"], grid, crs)}
    if semantics:
        tifs["bev_semantics.tif"] = lambda p: map_geotiff.write_semantics(p, bev["labels"], grid, crs)
    for c in cameras:
        tifs[f"bev_rgb_{c}.tif"] = lambda p, c=c: map_geotiff.write_rgb(p, bev["rgb"][c], np.isfinite(
            bev["elevation"]), grid, crs)
    for name, write in tifs.items():
        files[name] = write(out_dir / name)
    meta = {
        "origin_lat_lon_alt": [origin.lat_deg, origin.lon_deg, origin.alt_m] if origin is not None else None,
        "crs": crs,  # PROJ string of the GeoTIFFs' CRS, whose x, y are the ENU frame's (map_geotiff.local_crs)
        "origin_xy": bev["origin_xy"],
        "resolution_m": res,
        "shape": list(bev["elevation"].shape),
        "cell": ("cell (i, j) of the .npy rasters is centred at (x0 + j*res, y0 + i*res); PNGs and GeoTIFFs are "
                 "flipped north-up"),
        "semantics": semantics,  # false: the map has no semantics, and no bev_semantics.* files
        "semantics_no_label": NO_LABEL,
        "cameras": cameras,
    }
    (out_dir / "bev.json").write_text(json.dumps(meta, indent=2))
    files["bev.json"] = out_dir / "bev.json"

    return files


def _export_mesh(road_map: RoadMap, out_dir: Path, camera: str, origin_lat_lon_alt: list[float] | None
                 ) -> dict[str, Path]:
    """The observed part of the mesh with `camera`'s vertex colours and the labels (PLY, GLB), the checkpoint."""
    faces = road_map.mesh.faces[(road_map.observed[road_map.mesh.faces] > 0).all(1)]
    used, local = used_vertices(faces, road_map.mesh.num_vertices)
    vertices = np.concatenate([road_map.mesh.xy[used], road_map.z_now[used, None]], 1)
    colours = np.clip(road_map.vertex_colours(camera, used) * 255 + 0.5, 0, 255).astype(np.uint8)
    mesh = trimesh.Trimesh(vertices, local.reshape(-1, 3), vertex_colors=colours, process=False)
    if road_map.semantic_logits is not None:
        mesh.vertex_attributes["label"] = vertex_labels(road_map)[used]
    files = write_mesh_files(mesh, out_dir, origin_lat_lon_alt)
    torch.save(road_map.state_dict(), out_dir / "checkpoint.pt")
    files["checkpoint.pt"] = out_dir / "checkpoint.pt"
    return files
