"""Many drives' windows in the tile store merged into one map: each drive's windows fused into its own layer
(weighted by their confidences), each drive aligned to a reference drive (the one that mapped most) from their
overlap, then all layers fused per cell with their confidences, so that what one drive saw (under another's
parked car) fills the other's hole; each drive's cell counts by its supervising steps (DriveLayer.fusion_weight).

Alignment, per drive: the horizontal shift (up to MAX_SHIFT_M, below a cell: estimate_shift) that best overlays
its lane markings, curbs, manholes and road texture on the reference's, then the height plane (offset and tilt:
height_plane) between them there; the drives' consensus shift (to whole cells) and plane, each drive weighted by
the inverse variance of its fixes' reported accuracy (consensus_weights), are taken out of all of them (the map
lies where the drives agree, not where the reference drive's positioning put it). Class
probabilities move by whole cells, heights by the exact fraction (moved). Per camera, the appearance: an affine
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
from scipy.ndimage import gaussian_filter
from scipy.ndimage import shift as nd_shift

from daemon.spine.semantic_classes import NUM_MAP_CLASSES, SemanticClass
from mapping.fleet.fleet_journal import FleetJournal
from mapping.fleet.geodetic_grid import TILE_M, TileId, utm_crs
from mapping.fleet.tile_store import TileStore, save_json, save_npz
from mapping.live.map_images import atomic_png
from mapping.method.road_map import NO_LABEL
from mapping.outputs import map_geotiff
from mapping.outputs.map_colours import elevation_image, semantic_image

MAX_SHIFT_M = 0.5  # the largest horizontal shift between two drives searched for
ALIGNMENT_CLASSES = (SemanticClass.LANE_MARKING, SemanticClass.CURB, SemanticClass.MANHOLE)  # the shift's features
FEATURE_SMOOTH_CELLS = 1.0  # Gaussian sigma of the features the sub-cell shift is refined on
TEXTURE_SCALE_M = 1.0  # the road texture of the shift's features: luminance less its mean over this sigma
REFINE_STEPS = 8  # Gauss-Newton steps below a cell, at most
PRIOR_SHIFT_M = 0.25  # sigma of the prior on a drive's shift (two drives' RTK fixes agree that well)
PLANE_FITS = 3  # refits of the height plane between two drives without its outliers
PLANE_OUTLIER_MADS = 3.0  # a cell further off the plane than this many median absolute deviations is left out
GNSS_STD_FLOOR_M = 0.005  # a drive's reported GNSS accuracy counts no better than this in its consensus weight
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
    views: np.ndarray | None = None  # (H, W) float32 supervising steps (windows' exp(confidence) - 1, summed)
    gnss_std_m: tuple[float, float] | None = None  # (horizontal, vertical) its fixes' reported 1-sigma

    @property
    def fusion_weight(self) -> np.ndarray:
        """What the cell counts for in the fusion of drives: its supervising steps (the inverse variance of a mean
        of that many observations), so a cell one drive saw often and another barely takes the first one's."""
        return self.views if self.views is not None else self.weight

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
                                                   "n": np.zeros(shape, np.float32), "wp": None, "wrgb": {}})
                w = part.weight
                acc["w"][at] += w
                acc["n"][at] += np.expm1(w)
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
            entry = FleetJournal(store.root).drive(drive) or {}
            std = entry.get("gnss_std_m")
            mosaic.layers[drive] = DriveLayer(drive, height, w, prob, rgb, acc["n"],
                                              tuple(std) if std is not None else None)
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


def feature_image(layer: DriveLayer, cameras: list[str], resolution_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, channels) features the shift is estimated on, and where they hold (the labelled cells): the
    probabilities of ALIGNMENT_CLASSES and, per camera, the road's texture (luminance less its mean over
    TEXTURE_SCALE_M, over its spread there: another day's exposure, white balance and light do not change it;
    cracks, patches and stains give it structure along the road where paint has little), each smoothed over
    FEATURE_SMOOTH_CELLS inside the mask (thin markings widened into slopes the least squares can follow)."""
    labelled = (layer.mapped & (layer.prob.sum(-1) > 0)).astype(np.float32)
    mass = np.maximum(gaussian_filter(labelled, FEATURE_SMOOTH_CELLS), 1e-6)
    channels = [layer.prob[..., int(c)] for c in ALIGNMENT_CLASSES]
    scale = TEXTURE_SCALE_M / resolution_m
    wide = np.maximum(gaussian_filter(labelled, scale), 1e-6)
    for cam in cameras:
        luminance = layer.rgb[cam].mean(-1) * labelled
        detail = (luminance - gaussian_filter(luminance, scale) / wide) * labelled
        spread = np.sqrt(gaussian_filter(detail * detail, scale) / wide + 1.0)
        channels.append(detail / spread)
    feats = np.stack([gaussian_filter(c * labelled, FEATURE_SMOOTH_CELLS) for c in channels], -1)
    return feats / mass[..., None], labelled


def moved_features(feats: np.ndarray, mask: np.ndarray, di: float, dj: float) -> tuple[np.ndarray, np.ndarray]:
    """Features and mask moved by (di, dj) cells (bilinear); the mask keeps only cells moved in whole."""
    if float(di).is_integer() and float(dj).is_integer():
        return shifted(feats, int(di), int(dj), 0.0), shifted(mask, int(di), int(dj), 0.0) > 0.999
    m = nd_shift(mask, (di, dj), order=1, cval=0.0)
    f = np.stack([nd_shift(feats[..., k], (di, dj), order=1, cval=0.0) for k in range(feats.shape[-1])], -1)
    return f, m > 0.999


@dataclass
class ShiftEstimate:
    """The horizontal shift moving a drive onto the reference and how well the overlap constrains it."""

    shift: tuple[float, float] | None  # (di, dj) cells, sub-cell; None: no semantics or too little overlap
    overlap_cells: int
    cost_gain: float  # the cost at no shift less the cost at the shift
    std_m: tuple[float, float] = (np.nan, np.nan)  # along the least and the best constrained direction
    weak_direction_en: tuple[float, float] = (np.nan, np.nan)  # unit (east, north) of the least constrained


def estimate_shift(ref: DriveLayer, drive: DriveLayer, max_cells: int, resolution_m: float = 1.0) -> ShiftEstimate:
    """The shift moving `drive` onto `ref` (feature_image: the markings', curbs' and manholes' probabilities and
    the road's texture in every camera both have): the whole cells that overlay them best (least squares over the
    cells both labelled, each channel weighted by its own residual), then refined below a cell by Gauss-Newton
    (Lucas-Kanade). Its normal matrix sums the features' gradients: on a straight road the lines and curbs
    constrain only the across-road direction; dash ends, stop lines, manholes and the texture the along-road
    one, each with the weight of its own structure. A prior of PRIOR_SHIFT_M on the shift (the drives' GNSS
    agree that well) keeps a direction nothing constrains at no shift instead of at noise."""
    if ref.prob is None or drive.prob is None:
        return ShiftEstimate(None, 0, 0.0)
    both = ref.mapped & drive.mapped
    if both.sum() < MIN_OVERLAP_CELLS:
        return ShiftEstimate(None, int(both.sum()), 0.0)
    rows, cols = np.nonzero(both)
    pad = max_cells + int(4 * FEATURE_SMOOTH_CELLS)
    box = (slice(max(0, rows.min() - pad), rows.max() + pad + 1), slice(max(0, cols.min() - pad), cols.max() + pad + 1))
    cameras = sorted(set(ref.rgb) & set(drive.rgb))
    a, ma = feature_image(DriveLayer("", ref.height[box], ref.weight[box], ref.prob[box],
                                     {c: ref.rgb[c][box] for c in cameras}), cameras, resolution_m)
    b, mb = feature_image(DriveLayer("", drive.height[box], drive.weight[box], drive.prob[box],
                                     {c: drive.rgb[c][box] for c in cameras}), cameras, resolution_m)
    ma = ma > 0

    def residual(di: float, dj: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        bs, ms = moved_features(b, mb, di, dj)
        return bs, ma & ms, a - bs

    def cost(di: float, dj: float) -> float:
        _, m, diff = residual(di, dj)
        return float((diff[m] ** 2).sum(-1).mean()) if m.sum() >= MIN_OVERLAP_CELLS else np.inf

    def coarse_best() -> tuple[dict, tuple[int, int]]:
        costs = {(di, dj): cost(di, dj) for di in range(-max_cells, max_cells + 1)
                 for dj in range(-max_cells, max_cells + 1)}
        return costs, min(costs, key=costs.get)

    d = (0, 0)
    for _ in range(2):  # each channel weighted by its own residual (its noise): at no shift, then at the best one
        _, m, diff = residual(*d)
        spread = np.sqrt((diff[m] ** 2).mean(0)) + 1e-6
        a, b = a / spread, b / spread
        costs, d = coarse_best()
        if not np.isfinite(costs[d]):
            return ShiftEstimate(None, int(both.sum()), 0.0)
    d = np.array(d, float)
    prior_cells = PRIOR_SHIFT_M / resolution_m
    corr_cells = (2 * FEATURE_SMOOTH_CELLS + 1) ** 2  # neighbouring residuals are not independent
    for _ in range(REFINE_STEPS):
        bs, m, diff = residual(*d)
        gi, gj = np.gradient(bs, axis=(0, 1))
        g = np.stack([gi[m].ravel(), gj[m].ravel()], -1)  # d(moved b)/d(shift) = -gradient
        r = diff[m].ravel()
        noise = max(float(np.mean(r * r)), 1e-12) * corr_cells  # a featureless overlap: the prior alone
        normal = g.T @ g + noise / prior_cells**2 * np.eye(2)
        step = np.linalg.solve(normal, -(g.T @ r) - noise / prior_cells**2 * d)
        d = np.clip(d + step, -max_cells, max_cells)
        if np.abs(step).max() < 0.01:
            break
    variances, axes = np.linalg.eigh(noise * np.linalg.inv(normal))
    weak = axes[:, 1]  # (row = north, col = east) of the largest variance
    return ShiftEstimate((float(d[0]), float(d[1])), int(both.sum()), costs.get((0, 0), np.nan) - cost(*d),
                         tuple(float(np.sqrt(v) * resolution_m) for v in variances[::-1]),
                         (float(weak[1]), float(weak[0])))


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, cum[-1] / 2)])


def colour_map(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 3) affine colour map, least squares: [source, 1] @ map ~ target."""
    x = np.column_stack([source, np.ones(len(source))])
    return np.linalg.lstsq(x, target, rcond=None)[0]


def moved(layer: DriveLayer, di: float, dj: float) -> DriveLayer:
    """`layer` moved by (di, dj) cells. Its class probabilities, weights and colours move by the
    nearest whole cells (exactly: resampling a 15 cm line's probabilities at 20 cm cells spreads it over two cells
    below what its argmax keeps, measured: lane-marking IoU 41 -> 27 %); its heights, smooth, by the exact
    fraction (bilinear, confidence-weighted), where the whole-cell move mapped."""
    i, j = int(np.rint(di)), int(np.rint(dj))
    out = DriveLayer(layer.drive, shifted(layer.height, i, j, np.nan),
                     shifted(layer.weight, i, j, 0.0),
                     shifted(layer.prob, i, j, 0.0) if layer.prob is not None else None,
                     {c: shifted(v, i, j, 0.0) for c, v in layer.rgb.items()},
                     shifted(layer.views, i, j, 0.0) if layer.views is not None else None, layer.gnss_std_m)
    if float(di).is_integer() and float(dj).is_integer():
        return out
    w = layer.weight
    weight = nd_shift(w, (di, dj), order=1, cval=0.0)
    height = nd_shift(np.nan_to_num(layer.height) * w, (di, dj), order=1, cval=0.0) / np.where(weight > 0, weight, 1)
    fine = (weight > 1e-3 * max(float(w.max()), 1e-6)) & out.mapped
    out.height[fine] = height[fine].astype(np.float32)
    return out


def height_plane(ref: DriveLayer, layer: DriveLayer, origin: tuple[float, float]) -> np.ndarray | None:
    """ref's height less layer's where both mapped, as a plane: (offset at `origin` (row, col), m; slope per row,
    per column, m/cell), a least-squares fit weighted by the fusion weights, started at the weighted median and
    refitted PLANE_FITS times without the cells off it by more than PLANE_OUTLIER_MADS median absolute deviations
    (a curb's step half a cell apart, a parked car's edge); None: too little overlap."""
    both = ref.mapped & layer.mapped
    if both.sum() < MIN_OVERLAP_CELLS:
        return None
    rows, cols = np.nonzero(both)
    diff = (ref.height[both] - layer.height[both]).astype(np.float64)
    w = np.minimum(ref.fusion_weight[both], layer.fusion_weight[both]).astype(np.float64)
    x = np.column_stack([np.ones(len(rows)), rows - origin[0], cols - origin[1]])
    plane = np.array([weighted_median(diff, w), 0.0, 0.0])
    for _ in range(PLANE_FITS):
        residual = diff - x @ plane
        keep = np.abs(residual) <= PLANE_OUTLIER_MADS * max(float(np.median(np.abs(residual))), 1e-4)
        sw = np.sqrt(w[keep])
        plane = np.linalg.lstsq(x[keep] * sw[:, None], diff[keep] * sw, rcond=None)[0]
    return plane


def consensus_weights(layers: list[DriveLayer], axis: int) -> np.ndarray:
    """Each drive's say in where the map lies: the inverse variance of its fixes' reported accuracy (axis 0:
    horizontal, 1: vertical), so a drive on an RTK fix outweighs one on a float or stand-alone fix; equal weights
    where any drive reported none (nothing to weigh them by)."""
    stds = [layer.gnss_std_m for layer in layers]
    if any(s is None for s in stds):
        return np.ones(len(layers))
    return np.array([1.0 / max(s[axis], GNSS_STD_FLOOR_M) ** 2 for s in stds])


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
    """Every drive moved into the drives' consensus frame: each one's shift and height plane (offset and tilt)
    estimated against the reference, then their mean over the drives (the reference's own: zero), weighted by
    consensus_weights, taken out of all, so that no one drive's positioning or attitude error becomes the map's
    (independent errors average out) and a cell only one drive mapped carries the consensus tilt, not that
    drive's; colours onto the reference's."""
    max_cells = int(np.ceil(MAX_SHIFT_M / resolution_m))
    shifts: dict[str, tuple[float, float] | None] = {reference: (0.0, 0.0)}
    reports = {reference: {"drive": reference, "reference": True, "shift": "reference"}}
    for drive in sorted(set(layers) - {reference}):
        found = estimate_shift(layers[reference], layers[drive], max_cells, resolution_m)
        shifts[drive] = found.shift
        reports[drive] = {"drive": drive, "reference": False, "overlap_cells": found.overlap_cells,
                          "shift_cost_gain": found.cost_gain, "shift_std_m": list(found.std_m),
                          "least_constrained_direction_en": list(found.weak_direction_en),
                          "shift": "estimated" if found.shift else "not estimated: no semantics or too little overlap"}
    known = [d for d in sorted(shifts) if shifts[d] is not None]
    weights = consensus_weights([layers[d] for d in known], 0)
    mean_shift = np.average(np.array([shifts[d] for d in known], float), axis=0, weights=weights)
    ci, cj = (int(v) for v in np.rint(mean_shift))  # whole cells: the reference is moved without resampling
    placed = {}
    for drive, layer in layers.items():
        di, dj = shifts[drive] or (ci, cj)
        placed[drive] = moved(layer, di - ci, dj - cj)
        reports[drive]["shift_m"] = [(dj - cj) * resolution_m, (di - ci) * resolution_m]  # east, north
    rows, cols = np.nonzero(placed[reference].mapped)
    origin = (float(rows.mean()), float(cols.mean())) if len(rows) else (0.0, 0.0)
    planes = {reference: np.zeros(3)}
    for drive in sorted(set(layers) - {reference}):
        planes[drive] = height_plane(placed[reference], placed[drive], origin)
    known = [d for d in sorted(planes) if planes[d] is not None]
    weights = consensus_weights([layers[d] for d in known], 1)
    mean_plane = np.average(np.array([planes[d] for d in known]), axis=0, weights=weights)
    ii, jj = np.mgrid[0:placed[reference].height.shape[0], 0:placed[reference].height.shape[1]]
    out = []
    for drive in sorted(layers, key=lambda d: d != reference):
        plane = (planes[drive] if planes[drive] is not None else mean_plane) - mean_plane
        layer = placed[drive]
        layer.height = (layer.height + plane[0] + plane[1] * (ii - origin[0]) + plane[2] * (jj - origin[1])
                        ).astype(np.float32)
        reports[drive]["dz_m"] = float(plane[0])
        reports[drive]["tilt_cm_per_m"] = [float(plane[2] / resolution_m * 100), float(plane[1] / resolution_m * 100)]
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
    confidence_sum = np.zeros(shape, np.float32)
    h_sum = np.zeros(shape)
    p_sum = np.zeros((*shape, NUM_MAP_CLASSES), np.float32)
    rgb_sum: dict[str, np.ndarray] = {}
    rgb_w: dict[str, np.ndarray] = {}
    for layer in aligned:
        w = layer.fusion_weight
        w_sum += w
        confidence_sum += layer.weight
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
    return MergedMap(mosaic, height, confidence_sum, labels, confidence, rgb, reports, reference)


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
