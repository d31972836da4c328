"""The live worker's final map, `<data>/map/final`: the tiles' mosaic as rasters (.npy, and GeoTIFFs placed on the
earth: elevation and semantics at the grid's resolution, RGB at the overviews'), overview PNGs, a grid mesh (PLY,
GLB) and `metadata.json` (FinalMapMetadata: the one definition its writers and readers share). A map
none of whose windows had semantics (no masks, no model) has no bev_semantics.* files."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

from daemon.spine.local_frame import LocalFrame
from mapping.live import map_tiles
from mapping.live.map_images import atomic_png, atomic_write_text
from mapping.method.road_map import NO_LABEL
from mapping.outputs import map_geotiff
from mapping.outputs.map_annotation import annotated_map
from mapping.outputs.map_colours import elevation_image, elevation_range, semantic_image
from mapping.outputs.mesh_files import MESH_FILES, write_mesh_files

METADATA_NAME = "metadata.json"
OVERVIEW_MAX_CELLS = 4_000_000  # the final map's PNGs: an overview, coarser past 4 M cells of bounding box
CELL_CONVENTION = ("cell (i, j) of the .npy rasters is centred at (x0 + j*res, y0 + i*res); "
                   "PNGs and RGB GeoTIFFs (at png_resolution_m) and the other GeoTIFFs are flipped north-up")


@dataclass(frozen=True)
class TileStore:
    """Where the worker's finished windows are: its tile folder, tile size in cells, grid resolution, cameras."""

    folder: Path
    tile_cells: int
    resolution_m: float
    cameras: list[str]


@dataclass
class FinalMapMetadata:
    """`metadata.json` of a final map. The raster fields are absent (None) when no window was mapped."""

    windows: list[dict]  # the journal's window entries (mapping.live.worker_journal.WindowEntry as JSON)
    config: dict  # {"path": the config file, "sha256": its hash}
    distance_m: float  # the drive's length by wheel odometry
    origin_lat_lon_alt: list[float] | None  # the local ENU frame's origin (WGS84 deg, deg, m)
    origin_xy: list[float] | None = None  # ENU centre of raster cell (0, 0), m
    resolution_m: float | None = None  # raster cell size, m
    shape: list[int] | None = None  # raster (rows, columns)
    png_resolution_m: float | None = None  # the PNG overviews' cell size (coarser for a large map)
    cell: str | None = None  # the cell convention, in words
    semantics_no_label: int | None = None  # the class id of unmapped cells in bev_semantics.npy
    cameras: list[str] | None = None  # one bev_rgb_<camera>.png each
    mesh: dict | None = None  # the mesh files and sizes
    semantics: str | None = None  # "available", "partial: ..." or "unavailable: ..." (map_semantics); unavailable:
    # no bev_semantics.* files
    crs: str | None = None  # PROJ string of the GeoTIFFs' CRS (map_geotiff.local_crs; None: no origin known)

    def write(self, folder: Path) -> None:
        fields = {k: v for k, v in asdict(self).items() if v is not None or k == "origin_lat_lon_alt"}
        atomic_write_text(folder / METADATA_NAME, json.dumps(fields, indent=1, default=str))

    @staticmethod
    def read(folder: Path) -> FinalMapMetadata:
        """The metadata of the final map in `folder` (OSError if it has none, ValueError if unreadable)."""
        data = json.loads((folder / METADATA_NAME).read_text())
        if "origin_xy" in data:
            data["origin_xy"] = list(data["origin_xy"])
        return FinalMapMetadata(**data)


def map_semantics(windows: list[dict]) -> str:
    """What the final map's semantics rest on, from its done windows' `semantics` metrics (reconstruction.
    semantics_status; a window journalled before they were recorded counts as available)."""
    done = [w.get("metrics", {}).get("semantics", "available") for w in windows if w.get("status") == "done"]
    unavailable = sum(s.startswith("unavailable") for s in done)
    if unavailable == len(done):
        return f"unavailable: no window had frames with masks or a segmentation model ({len(done)} windows)"
    if unavailable or any(s.startswith("partial") for s in done):
        return f"partial: {unavailable} of {len(done)} windows without semantics, others from their masked frames"
    return "available"


def write_final_map(out: Path, tiles: TileStore, meta: FinalMapMetadata) -> Path:
    """Mosaic the tiles into `out` (rasters, PNGs, mesh) and write `meta`, completed with the rasters' grid."""
    out.mkdir(parents=True, exist_ok=True)
    if map_tiles.tile_indices(tiles.folder):
        meta.semantics = map_semantics(meta.windows)
        labelled = not meta.semantics.startswith("unavailable")
        grid = map_tiles.write_mosaic_npy(tiles.folder, tiles.tile_cells, tiles.resolution_m,
                                          {"elevation": out / "bev_elevation.npy"}
                                          | ({"labels": out / "bev_semantics.npy"} if labelled else {}))
        mos = map_tiles.mosaic(tiles.folder, tiles.tile_cells, tiles.resolution_m, tiles.cameras,
                               max_cells=OVERVIEW_MAX_CELLS)
        for name, image, annotation in overview_images(mos, tiles.cameras, labelled):
            atomic_png(out / f"{name}.png", image)
            atomic_png(out / f"{name}_annotated.png", annotated_map(image, mos.resolution_m, **annotation),
                       north_up=True)
        meta.crs = (map_geotiff.local_crs(LocalFrame(*meta.origin_lat_lon_alt))
                    if meta.origin_lat_lon_alt is not None else None)
        write_geotiffs(out, grid, mos, labelled, meta.crs)
        meta.origin_xy, meta.resolution_m, meta.shape = grid.origin_xy, grid.resolution_m, list(grid.shape)
        meta.png_resolution_m, meta.cell = mos.resolution_m, CELL_CONVENTION
        meta.semantics_no_label = NO_LABEL if labelled else None
        meta.cameras = tiles.cameras
        meta.mesh = write_mesh(out, tiles, meta.origin_lat_lon_alt)
    meta.write(out)
    return out


def overview_images(mos: map_tiles.Mosaic, cameras: list[str], labelled: bool) -> list[tuple[str, np.ndarray, dict]]:
    """(file name without .png, RGB raster, annotated_map's arguments) of each overview."""
    images = [(f"bev_rgb_{c}", mos.rgb[c], {"title": f"colour: {c}"}) for c in cameras]
    if labelled:
        images.append(("bev_semantics", semantic_image(mos.labels), {"title": "semantics", "legend": True}))
    return images + [("bev_elevation", elevation_image(mos.elevation),
                      {"title": "elevation", "elevation_range_m": elevation_range(mos.elevation)})]


def write_geotiffs(out: Path, grid: map_tiles.RasterGrid, mos: map_tiles.Mosaic, labelled: bool,
                   crs: str | None) -> None:
    """bev_elevation.tif and bev_semantics.tif from the .npy rasters (memory-mapped, written in blocks of rows),
    bev_rgb_<camera>.tif from the overview mosaic (at its resolution)."""
    at = (grid.origin_xy, grid.resolution_m)
    _atomic(out / "bev_elevation.tif", lambda p: map_geotiff.write_elevation(
        p, np.load(out / "bev_elevation.npy", mmap_mode="r"), at, crs))
    if labelled:
        _atomic(out / "bev_semantics.tif", lambda p: map_geotiff.write_semantics(
            p, np.load(out / "bev_semantics.npy", mmap_mode="r"), at, crs))
    for c, rgb in mos.rgb.items():
        _atomic(out / f"bev_rgb_{c}.tif", lambda p, rgb=rgb: map_geotiff.write_rgb(
            p, rgb, np.isfinite(mos.elevation), (mos.origin_xy, mos.resolution_m), crs))


def _atomic(path: Path, write) -> None:
    """`write(tmp)` then the finished file moved in place: a reader never opens half a GeoTIFF."""
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    tmp.replace(path)


def write_mesh(out: Path, tiles: TileStore, origin_lat_lon_alt: list[float] | None,
               max_vertices: int = 2_000_000) -> dict:
    """A grid mesh of the mapped cells (cells as vertices, two triangles per fully mapped 2x2 block),
    built from the tiles' mapped cells only."""
    cells = map_tiles.mapped_cells(tiles.folder, tiles.tile_cells, tiles.resolution_m, tiles.cameras[0],
                                  max_vertices)
    key = cells.i * (1 << 32) + (cells.j + (1 << 31))  # sorted, as the cells are

    def neighbour(di: int, dj: int) -> np.ndarray:
        """Index of the cell (i + di, j + dj) of every cell, -1 where it is not mapped."""
        k = key + di * (1 << 32) + dj
        pos = np.minimum(np.searchsorted(key, k), len(key) - 1)
        return np.where(key[pos] == k, pos, -1)

    a = np.arange(len(key))
    b, c, d = neighbour(0, 1), neighbour(1, 0), neighbour(1, 1)
    full = (b >= 0) & (c >= 0) & (d >= 0)
    faces = np.concatenate([np.stack([a[full], b[full], d[full]], 1), np.stack([a[full], d[full], c[full]], 1)])
    res = cells.resolution_m
    vertices = np.stack([cells.j * res, cells.i * res, cells.elevation], 1)
    mesh = trimesh.Trimesh(vertices, faces, vertex_colors=cells.rgb, process=False)
    write_mesh_files(mesh, out, origin_lat_lon_alt)
    return {"files": list(MESH_FILES), "vertices": len(vertices), "faces": len(faces),
            "resolution_m": res}
