"""Many drives' windows in the tile store merged into one map: each drive's windows fused into its own layer
(weighted by their confidences), each drive aligned to a reference drive (the one that mapped most) from their
overlap, then all layers fused per cell with their confidences, so that what one drive saw (under another's
parked car) fills the other's hole.

Alignment, per drive: the horizontal shift (whole cells, up to MAX_SHIFT_M) that best overlays its lane markings
and curbs on the reference's (the class probabilities of both, least squares over the cells both mapped), then
the elevation offset (the weighted median height difference there); the drives' mean shift and offset are taken
out of all of them (the map lies where the drives agree on average, not where the reference drive's positioning
put it). Per camera, the appearance: an affine
colour map (3 x 4, least squares) from the drive's colours to the reference's in the overlap. That affine map
stands in for the paper-style "one colour MLP per camera per drive over shared codes": each drive's own colour
MLPs have already absorbed its light and camera response, and what remains between two drives' renderings of
the same road (exposure, white balance, ambient light) is a smooth colour transform fitted from the overlap,
without refitting every drive's windows together. What it cannot take out: shadows that moved with the sun.

The merged tiles go to the store's merged/<tile>.npz (+ .json: the drives there); the map to OUT (map_geotiff:
GeoTIFFs in the UTM zone's CRS; .npy rasters; PNG overviews; metadata.json with every drive's alignment). The
layers are assembled per UTM zone over the zone's tiles in memory: docs/fleet.md says how this scales.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from daemon.spine.semantic_classes import NUM_MAP_CLASSES, SemanticClass
from mapping.fleet.geodetic_grid import TILE_M, TileId, utm_crs
from mapping.fleet.tile_store import TileStore, save_json, save_npz
from mapping.live.map_images import atomic_png
from mapping.method.road_map import NO_LABEL
from mapping.outputs import map_geotiff
from mapping.outputs.map_colours import elevation_image, semantic_image

MAX_SHIFT_M = 0.5  # the largest horizontal shift between two drives searched for
ALIGNMENT_CLASSES = (SemanticClass.LANE_MARKING, SemanticClass.CURB)  # what the shift is estimated from
MIN_OVERLAP_CELLS = 2000  # fewer cells mapped by both: no alignment (the drive is fused as it is)
COLOUR_SAMPLE = 200_000  # cells the colour maps are fitted on, at most


@dataclass
class DriveLayer:
    """One drive on a zone's mosaic: cell (i, j) centred at UTM (e0 + (j + 0.5) res, n0 + (i + 0.5) res)."""

    drive: str
    height: np.ndarray  # (H, W) float32 ellipsoidal m, NaN unmapped
    weight: np.ndarray  # (H, W) float32, 0 unmapped
    prob: np.ndarray | None  # (H, W, classes) float32 (zeros where unlabelled), None: no semantics
    rgb: dict[str, np.ndarray]  # camera -> (H, W, 3) float32 0..255

    @property
    def mapped(self) -> np.ndarray:
        return self.weight > 0


@dataclass
class ZoneMosaic:
    """The tiles of one UTM zone as one raster grid."""

    zone: int
    south: bool
    col0: int  # the lowest tile column and row
    row0: int
    shape: tuple[int, int]
    resolution_m: float
    tiles: list[TileId]
    layers: dict[str, DriveLayer] = field(default_factory=dict)

    @property
    def origin_xy(self) -> tuple[float, float]:
        """UTM centre of cell (0, 0)."""
        half = self.resolution_m / 2
        return self.col0 * TILE_M + half, self.row0 * TILE_M + half

    def tile_slice(self, tile: TileId, n: int) -> tuple[slice, slice]:
        r, c = (tile.row - self.row0) * n, (tile.col - self.col0) * n
        return slice(r, r + n), slice(c, c + n)


def drive_layers(store: TileStore) -> list[ZoneMosaic]:
    """Every drive's windows fused into its own layer, per UTM zone."""
    zones: dict[tuple[int, bool], list[TileId]] = defaultdict(list)
    for tile in store.tiles():
        zones[(tile.zone, tile.south)].append(tile)
    out = []
    for (zone, south), tiles in sorted(zones.items()):
        first = store.contributions(tiles[0])[0]
        n = store.read(tiles[0], first).height.shape[0]
        col0, row0 = min(t.col for t in tiles), min(t.row for t in tiles)
        shape = ((max(t.row for t in tiles) - row0 + 1) * n, (max(t.col for t in tiles) - col0 + 1) * n)
        mosaic = ZoneMosaic(zone, south, col0, row0, shape, TILE_M / n, tiles)
        sums: dict[str, dict] = {}
        for tile in tiles:
            at = mosaic.tile_slice(tile, n)
            for info in store.contributions(tile):
                part = store.read(tile, info)
                acc = sums.setdefault(info.drive, {"w": np.zeros(shape, np.float32), "wh": np.zeros(shape),
                                                   "wp": None, "wrgb": {}})
                w = part.weight
                acc["w"][at] += w
                acc["wh"][at] += np.where(w > 0, w * np.nan_to_num(part.height), 0)
                if part.class_prob is not None:
                    if acc["wp"] is None:
                        acc["wp"] = np.zeros((*shape, NUM_MAP_CLASSES), np.float32)
                    acc["wp"][at] += w[..., None] * part.class_prob / 255.0
                for cam, rgb in part.rgb.items():
                    acc["wrgb"].setdefault(cam, np.zeros((*shape, 3), np.float32))[at] += w[..., None] * rgb
        for drive, acc in sorted(sums.items()):
            w = acc["w"]
            safe = np.where(w > 0, w, 1)
            height = np.where(w > 0, acc["wh"] / safe, np.nan).astype(np.float32)
            prob = acc["wp"] / safe[..., None] if acc["wp"] is not None else None
            rgb = {cam: v / safe[..., None] for cam, v in acc["wrgb"].items()}
            mosaic.layers[drive] = DriveLayer(drive, height, w, prob, rgb)
        out.append(mosaic)
    return out


def shifted(array: np.ndarray, di: int, dj: int, fill) -> np.ndarray:
    """out[i, j] = array[i - di, j - dj] (cells moved by (di, dj)), `fill` where nothing moves in."""
    out = np.full_like(array, fill)
    h, w = array.shape[:2]
    src = (slice(max(0, -di), h - max(0, di)), slice(max(0, -dj), w - max(0, dj)))
    dst = (slice(max(0, di), h - max(0, -di)), slice(max(0, dj), w - max(0, -dj)))
    out[dst] = array[src]
    return out


def estimate_shift(ref: DriveLayer, drive: DriveLayer, max_cells: int) -> tuple[tuple[int, int] | None, int, float]:
    """((di, dj) moving `drive` onto `ref`, cells compared, the cost's gain over no shift) from the class
    probabilities of ALIGNMENT_CLASSES; None when either has no semantics or they overlap too little."""
    if ref.prob is None or drive.prob is None:
        return None, 0, 0.0
    channels = [int(c) for c in ALIGNMENT_CLASSES]
    both = ref.mapped & drive.mapped
    if both.sum() < MIN_OVERLAP_CELLS:
        return None, int(both.sum()), 0.0
    rows, cols = np.nonzero(both)
    pad = max_cells
    box = (slice(max(0, rows.min() - pad), rows.max() + pad + 1), slice(max(0, cols.min() - pad), cols.max() + pad + 1))
    a, b = ref.prob[box][..., channels], drive.prob[box][..., channels]
    ma, mb = ref.mapped[box] & (ref.prob[box].sum(-1) > 0), drive.mapped[box] & (drive.prob[box].sum(-1) > 0)
    costs = {}
    for di in range(-max_cells, max_cells + 1):
        for dj in range(-max_cells, max_cells + 1):
            m = ma & shifted(mb, di, dj, False)
            if m.sum() < MIN_OVERLAP_CELLS:
                continue
            diff = a[m] - shifted(b, di, dj, 0.0)[m]
            costs[(di, dj)] = float((diff * diff).sum(-1).mean())
    if not costs:
        return None, int(both.sum()), 0.0
    best = min(costs, key=costs.get)
    return best, int(both.sum()), costs.get((0, 0), np.nan) - costs[best]


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, cum[-1] / 2)])


def colour_map(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 3) affine colour map, least squares: [source, 1] @ map ~ target."""
    x = np.column_stack([source, np.ones(len(source))])
    return np.linalg.lstsq(x, target, rcond=None)[0]


def moved(layer: DriveLayer, di: int, dj: int, dz: float = 0.0) -> DriveLayer:
    """`layer` moved by (di, dj) cells and lifted by dz."""
    return DriveLayer(layer.drive, shifted(layer.height, di, dj, np.nan) + np.float32(dz),
                      shifted(layer.weight, di, dj, 0.0),
                      shifted(layer.prob, di, dj, 0.0) if layer.prob is not None else None,
                      {c: shifted(v, di, dj, 0.0) for c, v in layer.rgb.items()})


def height_offset(ref: DriveLayer, layer: DriveLayer) -> tuple[float | None, int]:
    """The weighted median of ref's height less layer's where both mapped (None: too little overlap)."""
    both = ref.mapped & layer.mapped
    if both.sum() < MIN_OVERLAP_CELLS:
        return None, int(both.sum())
    w = np.minimum(ref.weight[both], layer.weight[both])
    return weighted_median(ref.height[both] - layer.height[both], w), int(both.sum())


def recoloured(ref: DriveLayer, layer: DriveLayer) -> tuple[DriveLayer, dict]:
    """`layer`'s colours mapped onto `ref`'s appearance, per camera, from the cells both mapped."""
    both = ref.mapped & layer.mapped
    report = {}
    if both.sum() < MIN_OVERLAP_CELLS:
        return layer, report
    idx = np.flatnonzero(both.ravel())
    idx = idx if len(idx) <= COLOUR_SAMPLE else np.random.default_rng(0).choice(idx, COLOUR_SAMPLE, replace=False)
    for cam in sorted(set(ref.rgb) & set(layer.rgb)):
        src, dst = layer.rgb[cam].reshape(-1, 3)[idx], ref.rgb[cam].reshape(-1, 3)[idx]
        mapping = colour_map(src, dst)
        flat = layer.rgb[cam].reshape(-1, 3)
        layer.rgb[cam] = (np.column_stack([flat, np.ones(len(flat))]) @ mapping).reshape(layer.rgb[cam].shape)
        after = np.column_stack([src, np.ones(len(src))]) @ mapping
        report[cam] = {"map": mapping.round(4).tolist(), "rms_before": float(np.sqrt(((src - dst) ** 2).mean())),
                       "rms_after": float(np.sqrt(((after - dst) ** 2).mean()))}
    return layer, report


def aligned_layers(layers: dict[str, DriveLayer], reference: str, resolution_m: float
                   ) -> tuple[list[DriveLayer], list[dict]]:
    """Every drive moved into the drives' consensus frame: each one's shift and height offset estimated against
    the reference, then their mean over the drives (the reference's own: zero) taken out of all, so that no one
    drive's positioning error becomes the map's (independent errors average out); colours onto the reference's."""
    max_cells = int(np.ceil(MAX_SHIFT_M / resolution_m))
    shifts: dict[str, tuple[int, int] | None] = {reference: (0, 0)}
    reports = {reference: {"drive": reference, "reference": True, "shift": "reference"}}
    for drive in sorted(set(layers) - {reference}):
        shift, overlap, gain = estimate_shift(layers[reference], layers[drive], max_cells)
        shifts[drive] = shift
        reports[drive] = {"drive": drive, "reference": False, "overlap_cells": overlap, "shift_cost_gain": gain,
                          "shift": "estimated" if shift else "not estimated: no semantics or too little overlap"}
    known = np.array([s for s in shifts.values() if s is not None], float)
    ci, cj = (int(v) for v in np.rint(known.mean(0)))
    placed = {}
    for drive, layer in layers.items():
        di, dj = shifts[drive] or (ci, cj)
        placed[drive] = moved(layer, di - ci, dj - cj)
        reports[drive]["shift_m"] = [(dj - cj) * resolution_m, (di - ci) * resolution_m]  # east, north
    dz = {reference: 0.0}
    for drive in sorted(set(layers) - {reference}):
        dz[drive], _ = height_offset(placed[reference], placed[drive])
    mean_dz = float(np.mean([v for v in dz.values() if v is not None]))
    out = []
    for drive in sorted(layers, key=lambda d: d != reference):
        lift = (dz[drive] if dz[drive] is not None else mean_dz) - mean_dz
        layer = moved(placed[drive], 0, 0, lift)
        reports[drive]["dz_m"] = lift
        if drive != reference:
            layer, reports[drive]["colour"] = recoloured(placed[reference], layer)
        out.append(layer)
    return out, [reports[d] for d in sorted(layers, key=lambda d: d != reference)]


@dataclass
class MergedMap:
    """One zone's merged rasters (ZoneMosaic's cells)."""

    mosaic: ZoneMosaic
    height: np.ndarray  # float32 ellipsoidal m, NaN unmapped
    weight: np.ndarray  # float32 summed confidence
    labels: np.ndarray  # uint8 class ids, NO_LABEL unlabelled
    label_confidence: np.ndarray  # float32 the fused probability of the label
    rgb: dict[str, np.ndarray]  # uint8
    alignment: list[dict]
    reference: str


def fuse(mosaic: ZoneMosaic) -> MergedMap:
    """The zone's drives aligned to the one that mapped most cells and fused cell by cell."""
    layers = mosaic.layers
    reference = max(layers, key=lambda d: (int(layers[d].mapped.sum()), d))
    aligned, reports = aligned_layers(layers, reference, mosaic.resolution_m)
    shape = mosaic.shape
    w_sum = np.zeros(shape, np.float32)
    h_sum = np.zeros(shape)
    p_sum = np.zeros((*shape, NUM_MAP_CLASSES), np.float32)
    rgb_sum: dict[str, np.ndarray] = {}
    rgb_w: dict[str, np.ndarray] = {}
    for layer in aligned:
        w = layer.weight
        w_sum += w
        h_sum += np.where(w > 0, w * np.nan_to_num(layer.height), 0)
        if layer.prob is not None:
            p_sum += w[..., None] * layer.prob
        for cam, rgb in layer.rgb.items():
            rgb_sum.setdefault(cam, np.zeros((*shape, 3), np.float32))
            rgb_w.setdefault(cam, np.zeros(shape, np.float32))
            rgb_sum[cam] += w[..., None] * rgb
            rgb_w[cam] += w
    mapped = w_sum > 0
    height = np.where(mapped, h_sum / np.where(mapped, w_sum, 1), np.nan).astype(np.float32)
    p_total = p_sum.sum(-1)
    labelled = p_total > 0
    labels = np.where(labelled, p_sum.argmax(-1), NO_LABEL).astype(np.uint8)
    confidence = np.where(labelled, p_sum.max(-1) / np.where(labelled, p_total, 1), 0).astype(np.float32)
    rgb = {cam: np.clip(v / np.maximum(rgb_w[cam], 1e-6)[..., None] + 0.5, 0, 255).astype(np.uint8)
           for cam, v in rgb_sum.items()}
    return MergedMap(mosaic, height, w_sum, labels, confidence, rgb, reports, reference)


def merge_drives(store: TileStore, out: Path) -> dict:
    """Merge every drive in the store into merged/ tiles and the map files in `out`; the merge's report."""
    zones = []
    for mosaic in drive_layers(store):
        merged = fuse(mosaic)
        n = int(round(TILE_M / mosaic.resolution_m))
        for tile in mosaic.tiles:
            at = mosaic.tile_slice(tile, n)
            save_npz(store.merged_path(tile), {"height": merged.height[at], "weight": merged.weight[at],
                                               "labels": merged.labels[at],
                                               "label_confidence": merged.label_confidence[at],
                                               **{f"rgb_{c}": v[at] for c, v in merged.rgb.items()}})
            save_json(store.merged_path(tile).with_suffix(".json"),
                      {"tile": str(tile), "drives": sorted({i.drive for i in store.contributions(tile)}),
                       "reference": merged.reference})
        folder = out if len(zones) == 0 else out / f"zone_{mosaic.zone}{'S' if mosaic.south else 'N'}"
        zones.append(write_map(folder, merged))
    report = {"zones": zones}
    if zones:
        save_json(out / "metadata.json", report)
    return report


def write_map(out: Path, merged: MergedMap) -> dict:
    """The merged rasters of one zone as files; their description (metadata.json's zone entry)."""
    out.mkdir(parents=True, exist_ok=True)
    mosaic = merged.mosaic
    crs = utm_crs(mosaic.zone, mosaic.south).to_string()
    grid = (mosaic.origin_xy, mosaic.resolution_m)
    np.save(out / "bev_elevation.npy", merged.height)
    np.save(out / "bev_semantics.npy", merged.labels)
    map_geotiff.write_elevation(out / "bev_elevation.tif", merged.height, grid, crs)
    map_geotiff.write_semantics(out / "bev_semantics.tif", merged.labels, grid, crs)
    atomic_png(out / "bev_semantics.png", semantic_image(merged.labels))
    atomic_png(out / "bev_elevation.png", elevation_image(merged.height))
    for cam, rgb in merged.rgb.items():
        atomic_png(out / f"bev_rgb_{cam}.png", rgb)
        map_geotiff.write_rgb(out / f"bev_rgb_{cam}.tif", rgb, np.isfinite(merged.height), grid, crs)
    entry = {"zone": mosaic.zone, "south": mosaic.south, "crs": crs, "origin_xy": list(mosaic.origin_xy),
             "resolution_m": mosaic.resolution_m, "shape": list(mosaic.shape),
             "cell": "cell (i, j) of the .npy rasters is centred at UTM (x0 + j*res, y0 + i*res); heights ellipsoidal "
                     "(WGS84); PNGs and GeoTIFFs north up",
             "tiles": [str(t) for t in mosaic.tiles], "drives": sorted(mosaic.layers), "reference": merged.reference,
             "alignment": merged.alignment, "cells_mapped": int(np.isfinite(merged.height).sum()),
             "semantics_no_label": NO_LABEL}
    (out / "zone.json").write_text(json.dumps(entry, indent=1))
    return entry
