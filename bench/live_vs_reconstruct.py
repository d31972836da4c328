"""Live map against offline reconstruction: `roadlog replay` (recording + mapping worker) on a simulated drive,
then `roadlog reconstruct` on the log the daemon recorded, both measured the same way.

Both maps are taken as they come out, as BEV rasters on their own grids (the worker's `map/final`, the
reconstruction's export), and measured with one code path: PSNR of their renderings (each raster as a
mesh, per-camera colours) on road pixels at the reconstruction's held-out views (`psnr_db`: the live
map trained on them, it holds none out) and at 12 views both trained on (`psnr_train_db`, the fair
comparison), Elev-error (mean vertical distance from the recorded Lidar ground points to the raster
surface), the mean absolute elevation error against the simulator's true elevation and the bird's-eye
mIoU against its true semantic grid (every other 5 cm cell), each over what both maps cover.
`within_tolerance`: |gap| <= 0.5 dB (psnr_train_db), 0.5 cm (both elevation figures) and 5 points of
mIoU (the live map is made window by window). The reconstruction's own metrics (its renderer, its
coverage) are printed beside them. The reconstruction is made in the live map's frame (the truth moved into it,
`DriveTruth.in_frame`): both maps' grids then lie the same way against the truth's cells.
Drives are cached under /tmp/maplab/.

    .venv/bin/python bench/live_vs_reconstruct.py [--quick] [--scenario city] [--seconds 10]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.spine.config import load_config  # noqa: E402
from daemon.spine.local_frame import LocalFrame  # noqa: E402
from daemon.spine.semantic_classes import NUM_MAP_CLASSES, ROAD_SURFACE_CLASSES  # noqa: E402
from mapping.fits.reconstruction import select_keyframes  # noqa: E402
from mapping.live.final_map import FinalMapMetadata  # noqa: E402
from mapping.method.mesh_renderer import pixel_rays, rasterise, ray_triangle_weights, sampled_pixels, world_rays  # noqa: E402
from mapping.method.road_map import NO_LABEL  # noqa: E402
from mapping.method.scene_data import CameraModel, Keyframe  # noqa: E402
from mapping.offline.reconstruct_command import DriveTruth, run_reconstruction  # noqa: E402
from mapping.outputs.map_metrics import confusion, miou_pct, psnr_db, truth_cells  # noqa: E402

_spec = importlib.util.spec_from_file_location("mapping_bench", Path(__file__).with_name("mapping.py"))
mapping_bench = importlib.util.module_from_spec(_spec)  # its drive cache (simulated once, under /tmp/maplab)
_spec.loader.exec_module(mapping_bench)

HOLDOUT_EVERY = 10  # as `reconstruct` holds out its evaluation views
STRIDE = 2  # views rendered at every 2nd pixel row and column, as map_metrics does
VIEW_REACH_M = 35.0  # faces further from the camera are not drawn
TRAIN_VIEWS = 12  # as map_metrics evaluates training views
PSNR_TOLERANCE_DB, ELEV_TOLERANCE_CM, MIOU_TOLERANCE_PCT = 0.5, 0.5, 5.0


@dataclass(frozen=True)
class RasterMap:
    """A BEV map: cell (i, j) centred at (x0 + j*res, y0 + i*res) in the ENU frame `frame`."""

    elevation: np.ndarray
    labels: np.ndarray  # (H, W) uint8 class ids, NO_LABEL where unmapped
    rgb: dict[str, np.ndarray]  # camera -> (H, W, 3) uint8
    origin_xy: tuple[float, float]
    resolution_m: float
    frame: LocalFrame

    @staticmethod
    def load(folder: Path, meta: dict, frame: LocalFrame) -> RasterMap:
        if meta.get("png_resolution_m", meta["resolution_m"]) != meta["resolution_m"]:
            raise ValueError(f"{folder}: the colour PNGs are an overview ({meta['png_resolution_m']} m cells), "
                             f"coarser than the {meta['resolution_m']} m rasters: map too large for this bench")
        rgb = {}
        for cam in meta["cameras"]:
            image = cv2.imread(str(folder / f"bev_rgb_{cam}.png"), cv2.IMREAD_COLOR)
            rgb[cam] = np.flipud(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))  # the PNGs are north-up
        return RasterMap(np.load(folder / "bev_elevation.npy"), np.load(folder / "bev_semantics.npy"), rgb,
                         tuple(meta["origin_xy"]), float(meta["resolution_m"]), frame)

    def label_at(self, enu: np.ndarray, frame: LocalFrame) -> np.ndarray:
        """Class at each point given in `frame`: the class with the largest bilinear weight among the four cell
        centres around it (NO_LABEL where one of them is unmapped). The nearest cell alone would place a label
        up to half a cell off, and the maps' grids are offset differently from the truth's."""
        _, i0, j0, inside, corners = self._cells_around(enu, frame)
        votes, row = np.zeros((len(enu), NUM_MAP_CLASSES)), np.arange(len(enu))
        for di, dj, weight in corners:
            label = self.labels[i0 + di, j0 + dj]
            inside &= label < NUM_MAP_CLASSES
            votes[row, np.minimum(label, NUM_MAP_CLASSES - 1)] += weight  # one cell per row: no repeats
        return np.where(inside, votes.argmax(1), NO_LABEL).astype(np.uint8)

    def height_above(self, enu: np.ndarray, frame: LocalFrame) -> np.ndarray:
        """Height of points given in `frame` above the bilinear surface (NaN where a neighbour cell is unmapped)."""
        own, i0, j0, inside, corners = self._cells_around(enu, frame)
        z = sum(weight * self.elevation[i0 + di, j0 + dj] for di, dj, weight in corners)
        return np.where(inside, own[:, 2] - z, np.nan)

    def _cells_around(self, enu: np.ndarray, frame: LocalFrame):
        """Points given in `frame` in this map's frame (M, 3), the row and column of the cell centre below and
        left of each (clamped to 0 outside), whether all four centres around it are in the rasters, and the four
        corners as (row offset, column offset, bilinear weight)."""
        own = self._into_own_frame(enu, frame)
        f = (own[:, :2] - np.asarray(self.origin_xy)) / self.resolution_m
        j0, i0 = np.floor(f[:, 0]).astype(int), np.floor(f[:, 1]).astype(int)
        h, w = self.elevation.shape
        inside = (i0 >= 0) & (j0 >= 0) & (i0 < h - 1) & (j0 < w - 1)
        i0, j0 = np.where(inside, i0, 0), np.where(inside, j0, 0)
        fx, fy = f[:, 0] - j0, f[:, 1] - i0
        corners = ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy))
        return own, i0, j0, inside, corners

    def _into_own_frame(self, enu: np.ndarray, frame: LocalFrame) -> np.ndarray:
        return enu if frame == self.frame else self.frame.geodetic_to_enu(*frame.enu_to_geodetic(enu))

    def mesh_in(self, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Cells as vertices (in `frame`), two triangles per fully mapped 2x2 block, per-camera colours."""
        valid = np.isfinite(self.elevation)
        ii, jj = np.nonzero(valid)
        index = np.full(self.elevation.shape, -1, np.int64)
        index[valid] = np.arange(valid.sum())
        own = np.stack([self.origin_xy[0] + jj * self.resolution_m, self.origin_xy[1] + ii * self.resolution_m,
                        self.elevation[valid]], 1).astype(np.float64)
        vertices = own if frame == self.frame else frame.geodetic_to_enu(*self.frame.enu_to_geodetic(own))
        a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
        full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
        faces = np.concatenate([np.stack([a[full], b[full], d[full]], 1), np.stack([a[full], d[full], c[full]], 1)])
        return vertices, faces, {cam: rgb[valid].astype(np.float32) / 255.0 for cam, rgb in self.rgb.items()}


def render(mesh: tuple, keyframe: Keyframe, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (P, 3), hit (P,)) at the view's sampled pixels, exactly as map_metrics renders a road map."""
    vertices, faces, colours = mesh
    origin = keyframe.T_world_camera[:3, 3]
    near = np.linalg.norm(vertices[faces[:, 0], :2] - origin[:2], axis=1) < VIEW_REACH_M
    faces = faces[near]
    grid = rasterise(vertices, faces, camera, keyframe.T_world_camera, STRIDE).ravel()
    hit = grid >= 0
    rgb = np.zeros((len(grid), 3), np.float32)
    if hit.any():
        tri = faces[grid[hit]]
        pixels = sampled_pixels(camera, STRIDE).ravel()[hit]
        rays = world_rays(keyframe.T_world_camera, pixel_rays(camera)[pixels])
        w, _ = ray_triangle_weights(torch.from_numpy(rays), torch.from_numpy(vertices[tri] - origin))
        rgb[hit] = np.clip((colours[keyframe.camera][tri] * w.numpy()[..., None]).sum(1), 0, 1)
    return rgb, hit


def mean_psnr(meshes: dict[str, tuple], views: list[Keyframe], cameras: dict[str, CameraModel]) -> dict:
    """Mean PSNR per map over the views, on the road pixels that every map draws."""
    per_view: dict[str, list[float]] = {name: [] for name in meshes}
    road = np.array(ROAD_SURFACE_CLASSES)
    for kf in views:
        cam = cameras[kf.camera]
        at = sampled_pixels(cam, STRIDE).ravel()
        image = kf.image.reshape(-1, 3)[at].astype(np.float32) / 255.0
        rendered = {name: render(mesh, kf, cam) for name, mesh in meshes.items()}
        common = np.isin(kf.semantics.ravel()[at], road)
        for _, hit in rendered.values():
            common &= hit
        for name, (rgb, _) in rendered.items():
            value = psnr_db(rgb, image, common)
            if value is not None:
                per_view[name].append(value)
    return {name: float(np.mean(v)) if v else None for name, v in per_view.items()}


def compare(maps: dict[str, RasterMap], holdout: list[Keyframe], train: list[Keyframe],
            cameras: dict[str, CameraModel], lidar: np.ndarray, truth: DriveTruth) -> dict:
    """The figures of every map over what all of them cover (frame: the truth's). `psnr_db` at the views
    the reconstruction held out (the live map trained on them), `psnr_train_db` at views both trained on."""
    frame = truth.origin
    out: dict[str, dict] = {name: {} for name in maps}
    meshes = {name: m.mesh_in(frame) for name, m in maps.items()}
    for key, views in (("psnr_db", holdout), ("psnr_train_db", train)):
        for name, value in mean_psnr(meshes, views, cameras).items():
            out[name][key] = value
    # Elev-error: the recorded Lidar ground points
    dz = {name: m.height_above(lidar, frame) for name, m in maps.items()}
    both = np.logical_and.reduce([np.isfinite(v) for v in dz.values()])
    for name in maps:
        out[name]["elev_error_cm"] = float(100 * np.mean(np.abs(dz[name][both])))
        out[name]["lidar_points"] = int(both.sum())
    # against the true elevation, at the truth metrics' cells (every other 5 cm cell)
    rows, cols, xy = truth_cells(truth.elevation)
    true_z = truth.elevation.elevation_m[rows, cols]
    cells = np.concatenate([xy, np.nan_to_num(true_z)[:, None]], 1)
    dz = {name: m.height_above(cells, frame) for name, m in maps.items()}
    both = np.isfinite(true_z) & np.logical_and.reduce([np.isfinite(v) for v in dz.values()])
    for name in maps:
        out[name]["elev_mae_gt_cm"] = float(100 * np.mean(np.abs(dz[name][both])))
        out[name]["truth_cells"] = int(both.sum())
    # against the true semantic grid, the same cells
    true_label = truth.semantic[rows, cols]
    predicted = {name: m.label_at(cells, frame) for name, m in maps.items()}
    labelled = (true_label < NUM_MAP_CLASSES) & np.logical_and.reduce([p < NUM_MAP_CLASSES
                                                                       for p in predicted.values()])
    for name in maps:
        out[name]["miou_pct"] = miou_pct(confusion(predicted[name], true_label, labelled))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a 3 s drive (one window)")
    parser.add_argument("--scenario", default="city")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--keep", type=Path, help="keep the daemon's data and the reconstruction here")
    args = parser.parse_args()
    seconds = 3.0 if args.quick else args.seconds
    log = mapping_bench.drive(args.scenario, seconds)
    truth = DriveTruth.load(log.with_suffix(".gt.npz"))
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
        data["bus"] = {"shm_prefix": f"lvr{int(time.time() * 1000) % 10**9}"}
        data["status"]["port"] = 0
        for key in ("metadata_file",):
            data["sensors"]["lidar"][key] = str(ROOT / "configs" / data["sensors"]["lidar"][key])
        data["sensors"]["can"]["dbc_file"] = str(ROOT / "configs" / data["sensors"]["can"]["dbc_file"])
        config_path = work / "car.yaml"
        config_path.write_text(yaml.safe_dump(data))
        config = load_config(config_path)

        started = time.monotonic()
        subprocess.run([sys.executable, "-m", "daemon.commands.cli", "replay", str(log), "--config", str(config_path),
                        "--rate", "max", "--output-dir", str(work / "data")], check=True, cwd=ROOT,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        live_wall = time.monotonic() - started
        final = work / "data" / "map" / "final"
        live_meta = FinalMapMetadata.read(final)
        recorded = sorted(str(p) for p in (work / "data").glob("*.mcap"))
        # the reconstruction in the live map's frame: each map's 10 cm raster sits on its own frame's origin, and
        # where its cells fall relative to the truth's moves the mIoU by points (the thin lane markings): the same
        # reconstruction of city3 reads 82.7 % in the truth's frame, 77.0 % in the live map's (2026-12-06)
        live_frame = LocalFrame(*live_meta.origin_lat_lon_alt)
        truth = truth.in_frame(live_frame)

        started = time.monotonic()
        result, drive = run_reconstruction(recorded, work / "reconstruct", config, config_path, truth=truth,
                                           progress=False)
        reconstruct_wall = time.monotonic() - started
        rec_meta = json.loads((work / "reconstruct" / "bev.json").read_text())

        maps = {"live": RasterMap.load(final, asdict(live_meta), live_frame),
                "reconstruct": RasterMap.load(work / "reconstruct", rec_meta, truth.origin)}
        selected = select_keyframes(drive.keyframes, drive.path, config.mapper.inputs.keyframe_spacing_m)
        held = [i % HOLDOUT_EVERY == HOLDOUT_EVERY // 2 for i in range(len(selected))]
        holdout = [k for k, h in zip(selected, held, strict=True) if h]
        train = [k for k, h in zip(selected, held, strict=True) if not h]
        train = [train[i] for i in np.linspace(0, len(train) - 1, min(len(train), TRAIN_VIEWS)).astype(int)]
        figures = compare(maps, holdout, train, drive.cameras, drive.lidar_ground_points, truth)

    live, rec = figures["live"], figures["reconstruct"]
    keys = ("psnr_db", "psnr_train_db", "elev_error_cm", "elev_mae_gt_cm", "miou_pct")
    gaps = {f"{k}_gap": (live[k] - rec[k]) if live[k] is not None and rec[k] is not None else None for k in keys}
    within = (gaps["psnr_train_db_gap"] is not None and abs(gaps["psnr_train_db_gap"]) <= PSNR_TOLERANCE_DB
              and abs(gaps["elev_error_cm_gap"]) <= ELEV_TOLERANCE_CM
              and abs(gaps["elev_mae_gt_cm_gap"]) <= ELEV_TOLERANCE_CM
              and gaps["miou_pct_gap"] is not None and abs(gaps["miou_pct_gap"]) <= MIOU_TOLERANCE_PCT)
    native = {k: result.metrics.get(k) for k in keys}
    print(f"{'':<14}" + "".join(f"{k:>16}" for k in keys))
    for name, f in [*figures.items(), ("reconstruct*", native)]:
        print(f"{name:<14}" + "".join(f"{f[k] if f[k] is not None else float('nan'):>16.2f}" for k in keys))
    print("(* the reconstruction's own metrics: its renderer, its coverage)")
    print(json.dumps({"drive": log.name, "drive_s": drive.drive_s, "windows": len(live_meta.windows),
                      "live": live, "reconstruct": rec, "reconstruct_native": native, **gaps,
                      "within_tolerance": within, "live_wall_s": live_wall,
                      "reconstruct_wall_s": reconstruct_wall}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
