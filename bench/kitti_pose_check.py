"""Is camera-only KITTI 01's 1-3 px misregistration the map's surface or the drive's recorded poses? Three
measurements:

1. **Per-view rigid alignment against the frozen map.** 01 is imported and mapped in-process (camera only, as
   bench/kitti.py --quick). For each held-out view and each training view, a rigid correction of that one view's
   pose (camera frame: lateral x, vertical y (down), along-track z; pitch about x, yaw about y, roll about z) is
   fitted to the frozen map: the map's surface points and rendered grey that the view sees at its recorded pose are
   projected into its (blurred, coarse to fine) image through the corrected pose (optionally with a free gain and
   offset), minimising the squared difference (torch L-BFGS; unbounded and ill-conditioned on a planar road: at a map's
   last view it can slide a metre along the track, where the evaluated pixels change); and by a bounded coordinate
   search on the metric's own PSNR (the figure to use), with its basin checked from an offset start for held-out
   views; and each axis alone, scanned.
   Per view: the correction, the view's PSNR (the metric's pixels, re-rendered at the corrected pose, no gain)
   before and after, and the PSNR with 48x24-px tiles (of the 2x evaluation grid) each shifted by up to 3 px to
   their best fit, before and after the rigid correction (how much of the tile gain one rigid correction takes).
2. **Geometry that does not use our map** (bench/kitti_image_geometry.py): SIFT matches between consecutive raw
   frames (and frames 2 apart); per pair the Sampson epipolar error (px) of the matches under the recorded relative
   pose and under an essential matrix fitted to them (RANSAC), and the fitted relative rotation and translation
   direction against the recorded ones (deg; the direction's difference times the step in cm); the same Sampson error
   with each view's map-fitted correction applied to its frame (a real pose error would lower it). Along-track
   (invisible to epipolar geometry): the road's plane-induced homography between consecutive frames (step / camera
   height per pair) and the recorded track's steps against a smooth fit (speed jitter, cm). `--tiles`: where the
   tiles' shifts are (distance band, image third, markings) and how far along the radial (epipolar) lines.
3. The held-out PSNR with every held-out view's pose first aligned to the frozen map (test-time pose alignment,
   as pose-refining NeRF papers evaluate): a second figure, not the benchmark's. `--refined` also maps with
   `mapper.pose_refinement` on and aligns its held-out views the same way.

    .venv/bin/python bench/kitti_pose_check.py [--quick] [--refined] [--seed 0] [--tiles] [--skip-map]

Without `--quick`: the held-out views and every 3rd training view (~20 min at a load of 5 on 2 cores); `--quick`:
every 4th, no frames-2-apart pairs. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.ndimage import gaussian_filter

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from kitti_error import HOLDOUT_EVERY, ROADLOG, mapped_once, with_seed  # noqa: E402
from kitti_image_geometry import FOLDER, correction_matrix, epipolar, epipolar_of_corrections, rotation  # noqa: E402

from mapping.fits.pose_refinement import corrected  # noqa: E402
from mapping.fits.reconstruction import select_keyframes  # noqa: E402
from mapping.method.road_map import WindowIndex, view_rgb  # noqa: E402
from mapping.offline.reconstruct_command import config_from_logs  # noqa: E402
from mapping.outputs.map_metrics import EVAL_STRIDE, _view_score, _view_seen  # noqa: E402

TILE = (24, 48)  # rows, columns of the 2x evaluation grid
TILE_SHIFT = 3  # px of that grid, each way
BLURS_PX = (4.0, 2.0, 1.0, 0.0)  # full-resolution Gaussian sigma, coarse to fine
SEARCH_STEPS = np.array([0.75, 0.75, 0.75, 1.0, 1.0, 2.0])  # mrad (0.043 deg), cm: the coarsest search steps
NAMES = ("pitch_deg", "yaw_deg", "roll_deg", "lateral_cm", "down_cm", "along_cm")


def db(mse: float) -> float:
    return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))


class View:
    """One keyframe against the frozen map: what it sees at its recorded pose."""

    def __init__(self, road_map, drive, windows, mapped, kf, w):
        self.road_map, self.drive, self.windows, self.mapped, self.w = road_map, drive, windows, mapped, w
        self.kf = kf
        seen = self.seen(kf)
        g = seen.geometry
        road = seen.road_pixels.ravel()[g.hit]
        verts = np.concatenate([road_map.mesh.xy, road_map.z_now[:, None].astype(np.float64)], 1)
        self.points = (verts[g.tri[road]] * g.weights.numpy()[road][..., None]).sum(1)
        self.grid_shape = g.shape
        self.pix = np.flatnonzero(g.hit)[road]  # flat index into the (H', W') grid
        grey = view_rgb(road_map, g, seen.camera).mean(-1)
        self.render = grey  # (H', W')
        self.mask = np.zeros(g.shape[0] * g.shape[1], bool)
        self.mask[self.pix] = True
        self.mask = self.mask.reshape(g.shape)
        cam = drive.cameras[kf.camera]
        self.K = cam.K
        self.image = kf.image.astype(np.float64).mean(-1) / 255.0

    def seen(self, kf):
        return _view_seen(self.road_map, self.drive.cameras, kf, self.drive.path, self.w.before_m, self.w.after_m,
                          self.windows, self.mapped)

    def psnr(self, p: np.ndarray | None = None) -> tuple[float, float]:
        """(PSNR, PSNR with tile shifts) of the view re-rendered at its pose corrected by `p`."""
        kf = self.kf if p is None else dataclasses.replace(
            self.kf, T_world_camera=self.kf.T_world_camera @ correction_matrix(p))
        seen = self.seen(kf)
        score = _view_score(self.road_map, seen)
        rend = view_rgb(self.road_map, seen.geometry, seen.camera).mean(-1)
        return score.psnr, tile_psnr(rend, seen.observed.mean(-1), seen.road_pixels)

    def align(self, free: np.ndarray, iters: int = 30, photometric: bool = False,
              start: np.ndarray | None = None) -> np.ndarray:
        """The correction (mrad, cm) minimising the view's photometric error against the frozen map (the view's
        pose taken as its recorded pose corrected by `start`); `photometric`: with a free gain and offset."""
        T = self.kf.T_world_camera if start is None else self.kf.T_world_camera @ correction_matrix(start)
        xc = torch.from_numpy((self.points - T[:3, 3]) @ T[:3, :3])  # in the recorded camera frame
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        h, w = self.image.shape
        params = torch.zeros(8, dtype=torch.float64, requires_grad=True)  # 6 pose, gain, offset
        keep = torch.from_numpy(np.concatenate([free, [1.0, 1.0] if photometric else [0.0, 0.0]]))
        for sigma in BLURS_PX:
            img = gaussian_filter(self.image, sigma) if sigma > 0 else self.image
            s = sigma / EVAL_STRIDE
            if s > 0:
                norm = gaussian_filter(self.mask.astype(np.float64), s)
                rend = gaussian_filter(self.render * self.mask, s) / np.maximum(norm, 1e-6)
            else:
                rend = self.render
            target = torch.from_numpy(rend.ravel()[self.pix].astype(np.float64))
            image = torch.from_numpy(img)[None, None]

            def loss(image=image, target=target):
                p = params * keep
                r = rotation(p[:3] * 1e-3)
                x = (xc - p[3:6] * 1e-2) @ r  # R^T (x - t), row vectors
                z = x[:, 2].clamp(min=0.5)
                u, v = fx * x[:, 0] / z + cx, fy * x[:, 1] / z + cy
                inside = (u > 1) & (u < w - 2) & (v > 1) & (v < h - 2)
                grid = torch.stack([u / (w - 1) * 2 - 1, v / (h - 1) * 2 - 1], -1)[None, None]
                seen = torch.nn.functional.grid_sample(image, grid, align_corners=True)[0, 0, 0]
                res = seen - ((1 + p[6]) * target + p[7])
                return (res[inside] ** 2).mean()

            opt = torch.optim.LBFGS([params], max_iter=iters, line_search_fn="strong_wolfe")

            def closure(opt=opt, loss=loss):
                opt.zero_grad()
                value = loss()
                value.backward()
                return value

            opt.step(closure)
        p = (params * keep).detach().numpy()[:6]
        if start is None:
            return p
        total = correction_matrix(start) @ correction_matrix(p)  # back to a correction of the recorded pose
        return np.r_[1e3 * cv2.Rodrigues(total[:3, :3])[0].ravel(), 1e2 * total[:3, 3]]

    def metric(self, p: np.ndarray) -> float:
        kf = dataclasses.replace(self.kf, T_world_camera=self.kf.T_world_camera @ correction_matrix(p))
        return _view_score(self.road_map, self.seen(kf)).psnr

    def search(self, start: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """A rigid correction found by coordinate search on the metric's PSNR itself (the view re-rendered at each
        candidate): axis by axis, SEARCH_STEPS wide, then finer; (correction, its PSNR)."""
        p = np.zeros(6) if start is None else start.copy()
        best = self.metric(p)
        for scale, reach in ((1.0, 3), (0.5, 2), (0.25, 2)):
            for axis in range(6):
                centre = p.copy()
                for k in [i for i in range(-reach, reach + 1) if i]:
                    q = centre.copy()
                    q[axis] += k * scale * SEARCH_STEPS[axis]
                    value = self.metric(q)
                    if value > best:
                        best, p = value, q
        return p, best

    def scan(self, axis: int, values: np.ndarray) -> tuple[float, float]:
        """The metric's PSNR with the pose corrected along one axis only, at each of `values` (mrad or cm):
        (best value, its PSNR)."""
        best = (0.0, -np.inf)
        for value in values:
            p = np.zeros(6)
            p[axis] = value
            kf = dataclasses.replace(self.kf, T_world_camera=self.kf.T_world_camera @ correction_matrix(p))
            psnr = _view_score(self.road_map, self.seen(kf)).psnr
            if psnr > best[1]:
                best = (float(value), psnr)
        return best


def tile_psnr(rend: np.ndarray, obs: np.ndarray, mask: np.ndarray) -> float:
    """PSNR with each TILE of the render shifted by up to TILE_SHIFT px (its best fit over its masked pixels)."""
    hh, ww = rend.shape
    s = TILE_SHIFT
    pr = np.pad(rend, s)
    pm = np.pad(mask, s)
    best = np.full((hh // TILE[0] + 1, ww // TILE[1] + 1), np.inf)
    counts = np.zeros_like(best)
    for dy in range(-s, s + 1):
        for dx in range(-s, s + 1):
            r = pr[s + dy:s + dy + hh, s + dx:s + dx + ww]
            ok = mask & pm[s + dy:s + dy + hh, s + dx:s + dx + ww]
            err = np.where(ok, (r - obs) ** 2, 0.0)
            for i in range(best.shape[0]):
                for j in range(best.shape[1]):
                    sl = (slice(i * TILE[0], (i + 1) * TILE[0]), slice(j * TILE[1], (j + 1) * TILE[1]))
                    n = ok[sl].sum()
                    if n < 0.5 * mask[sl].sum() or n == 0:
                        continue
                    m = err[sl].sum() / n
                    if m < best[i, j]:
                        best[i, j], counts[i, j] = m, mask[sl].sum()
    keep = np.isfinite(best)
    return db(float((best[keep] * counts[keep]).sum() / counts[keep].sum()))


def tile_pattern(rend: np.ndarray, obs: np.ndarray, mask: np.ndarray, dist: np.ndarray) -> list[dict]:
    """Per TILE: its best shift (dy, dx) of the render, the squared error at no shift and at the best, its median
    distance, and the gain cross-validated (the shift chosen on the even columns, scored on the odd, and back)."""
    hh, ww = rend.shape
    s = TILE_SHIFT
    pr, pm = np.pad(rend, s), np.pad(mask, s)
    cols = np.arange(ww)[None, :] % 2 == 0
    tiles = []
    for i in range(0, hh, TILE[0]):
        for j in range(0, ww, TILE[1]):
            sl = (slice(i, i + TILE[0]), slice(j, j + TILE[1]))
            m = mask[sl]
            if m.sum() < 100:
                continue
            errs = {}
            for dy in range(-s, s + 1):
                for dx in range(-s, s + 1):
                    r = pr[s + dy:s + dy + hh, s + dx:s + dx + ww][sl]
                    ok = m & pm[s + dy:s + dy + hh, s + dx:s + dx + ww][sl]
                    if ok.sum() < 0.9 * m.sum():
                        continue
                    e = (r - obs[sl]) ** 2
                    ev, od = ok & cols[:, j:j + TILE[1]], ok & ~cols[:, j:j + TILE[1]]
                    errs[(dy, dx)] = (e[ok].mean(), e[ev].mean() if ev.any() else np.inf,
                                      e[od].mean() if od.any() else np.inf)
            best = min(errs, key=lambda k: errs[k][0])
            on_even = min(errs, key=lambda k: errs[k][1])
            on_odd = min(errs, key=lambda k: errs[k][2])
            tiles.append({"dy": best[0], "dx": best[1], "n": int(m.sum()), "err0": float(errs[(0, 0)][0]),
                          "err_best": float(errs[best][0]),
                          "err_cv": float(0.5 * (errs[on_even][2] + errs[on_odd][1])),
                          "dist": float(np.median(dist[sl][m])), "col": (j + TILE[1] / 2) / ww,
                          "centre": (i + TILE[0] / 2, j + TILE[1] / 2),
                          "bright": float((obs[sl][m] > 0.6).mean())})
    return tiles


def tiles_report(road_map, drive, config, selected, label: str) -> dict:
    """The tiles' best shifts and their gains by distance band, pooled over `selected` views."""
    windows = WindowIndex.of(road_map.mesh)
    mapped = (road_map.observed[road_map.mesh.faces] > 0).all(1)
    tiles = []
    for kf in selected:
        seen = _view_seen(road_map, drive.cameras, kf, drive.path, config.mapper.windows.before_m,
                          config.mapper.windows.after_m, windows, mapped)
        rend = view_rgb(road_map, seen.geometry, seen.camera).mean(-1)
        tiles += tile_pattern(rend, seen.observed.mean(-1), seen.road_pixels, seen.distance_m)
    out = {}
    groups = [(f"{lo}-{hi} m", lambda x, lo=lo, hi=hi: lo <= x["dist"] < hi)
              for lo, hi in ((5, 10), (10, 15), (15, 20), (20, 40), (0, 1000))]
    groups += [("left third", lambda x: x["col"] < 1 / 3), ("middle third", lambda x: 1 / 3 <= x["col"] < 2 / 3),
               ("right third", lambda x: x["col"] >= 2 / 3),
               ("tiles with markings (> 5 % of pixels above 0.6 grey)", lambda x: x["bright"] > 0.05),
               ("tiles without", lambda x: x["bright"] <= 0.05)]
    for name, which in groups:
        t = [x for x in tiles if which(x)]
        if not t:
            continue
        n = np.array([x["n"] for x in t], float)

        def pooled(key, t=t, n=n):
            return db(float((np.array([x[key] for x in t]) * n).sum() / n.sum()))

        dy, dx = np.array([x["dy"] for x in t]), np.array([x["dx"] for x in t])
        # each tile's shift split along / across the radial line from the focus of expansion (about the
        # principal point for this forward motion): a wrong depth (surface height) moves content along the
        # epipolar lines, i.e. radially; a rotation or a sideways translation error moves it across them too
        focus = np.array([185.2, 607.2]) / EVAL_STRIDE
        radial = np.array([x["centre"] for x in t]) - focus
        radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
        along_r = dy * radial[:, 0] + dx * radial[:, 1]
        across_r = -dy * radial[:, 1] + dx * radial[:, 0]
        band = {"tiles": len(t), "psnr_db": round(pooled("err0"), 2), "tile_gain_db": round(pooled("err_best")
                                                                                          - pooled("err0"), 2),
                "cross_validated_gain_db": round(pooled("err_cv") - pooled("err0"), 2),
                "shifted_pct": round(100 * float(np.mean((dy != 0) | (dx != 0))), 1),
                "mean_abs_dy_px": round(float(np.abs(dy).mean()), 2),
                "mean_abs_dx_px": round(float(np.abs(dx).mean()), 2),
                "mean_dy_px": round(float(dy.mean()), 2), "mean_dx_px": round(float(dx.mean()), 2),
                "radial_share_of_shift_pct": round(100 * float((along_r ** 2).sum()
                                                               / max((along_r ** 2 + across_r ** 2).sum(), 1e-9)), 1)}
        band["pixels_pct"] = round(100 * float(n.sum()) / sum(x["n"] for x in tiles), 1)
        band["error_share_pct"] = round(100 * float(sum(x["err0"] * x["n"] for x in t))
                                        / sum(x["err0"] * x["n"] for x in tiles), 1)
        out[name] = band
        print(f"  {label} tiles, {name}: {band}", flush=True)
    return out


def report(p: np.ndarray) -> dict:
    return {"pitch_deg": round(float(np.degrees(p[0] * 1e-3)), 3), "yaw_deg": round(float(np.degrees(p[1] * 1e-3)), 3),
            "roll_deg": round(float(np.degrees(p[2] * 1e-3)), 3), "lateral_cm": round(float(p[3]), 2),
            "down_cm": round(float(p[4]), 2), "along_cm": round(float(p[5]), 2)}


_RAW: dict[bytes, int] = {}


def frame_of(kf) -> int:
    """The keyframe's frame number in the raw sequence (its image found among the raw frames; the imported drive
    holds 36 of the 51)."""
    if not _RAW:
        for i, f in enumerate(sorted((FOLDER / "image_0").glob("*.png"))):
            _RAW[cv2.imread(str(f), cv2.IMREAD_GRAYSCALE).tobytes()] = i
    return _RAW[np.ascontiguousarray(kf.image[..., 0]).tobytes()]


def map_alignment(log: Path, seed: int, quick: bool, refined: bool) -> dict:
    config, config_path = config_from_logs([str(log)])
    config = with_seed(config, seed)
    if refined:
        mapper = config.mapper
        config = config.model_copy(update={"mapper": mapper.model_copy(update={
            "pose_refinement": mapper.pose_refinement.model_copy(update={"enabled": True})})})
    result, drive, _ = mapped_once(log, config, config_path)
    road_map, m = result.road_map, result.metrics
    selected = select_keyframes(drive.keyframes, drive.path, config.mapper.inputs.keyframe_spacing_m)
    held = [k for i, k in enumerate(selected) if i % HOLDOUT_EVERY == HOLDOUT_EVERY // 2]
    train = [k for i, k in enumerate(selected) if i % HOLDOUT_EVERY != HOLDOUT_EVERY // 2]
    if refined and result.pose_corrections is not None:  # the views as the run evaluated (held-out) / used them
        held = corrected(held, drive.path, result.pose_corrections)
        train = corrected(train, drive.path, result.pose_corrections)
    windows = WindowIndex.of(road_map.mesh)
    mapped = (road_map.observed[road_map.mesh.faces] > 0).all(1)
    tag = "refined" if refined else "recorded"
    print(f"map ({tag} poses, seed {seed}): held-out {m['psnr_db']:.2f} dB on {len(held)} views, train "
          f"{m['psnr_train_db']:.2f}; {len(selected)} keyframes selected", flush=True)
    views = [("held", k) for k in held] + [("train", k) for k in (train[::4] if quick else train[::3])]
    if refined:
        views = [("held", k) for k in held]
    rows = []
    inject = np.array([2.6, 0.0, 0.0, 3.0, 0.0, 5.0])  # pitch 0.15 deg, lateral 3 cm, along 5 cm
    for kind, kf in views:
        started = time.perf_counter()
        v = View(road_map, drive, windows, mapped, kf, config.mapper.windows)
        before, tile_before = v.psnr()
        p6 = v.align(np.ones(6))
        after, tile_after = v.psnr(p6)
        row = {"kind": kind, "frame": frame_of(kf), "pixels": len(v.pix), "psnr_db": round(before, 2),
               "tile_psnr_db": round(tile_before, 2), "aligned_6dof": report(p6), "psnr_6dof_db": round(after, 2),
               "tile_psnr_6dof_db": round(tile_after, 2)}
        line = ""
        ps, best = v.search()
        row["searched"] = report(ps)
        row["psnr_searched_db"] = round(best, 2)
        row["tile_psnr_searched_db"] = round(v.psnr(ps)[1], 2)
        line = f"; searched on the metric {best:.2f} dB (tiles {row['tile_psnr_searched_db']:.2f}): " + " ".join(
            f"{k} {x:+g}" for k, x in row["searched"].items())
        if not refined:
            if kind == "held":  # the search's basin: started 0.15 deg / 3 cm / 5 cm off, does it come back?
                row["psnr_offset_start_db"] = round(v.metric(inject), 2)
                back, value = v.search(inject)
                row["from_offset_start"] = report(back)
                row["psnr_from_offset_start_db"] = round(value, 2)
                line += (f"; started 0.15 deg pitch / 3 cm lateral / 5 cm along off ({row['psnr_offset_start_db']:.2f}"
                         f" dB), the search ends at {value:.2f} dB, " + " ".join(
                             f"{k} {x:+g}" for k, x in row["from_offset_start"].items()))
            scans = {}
            for axis, values in enumerate([np.arange(-3, 3.01, 0.75)] * 3 + [np.arange(-4, 4.01, 1.0)] * 2
                                          + [np.arange(-8, 8.01, 2.0)]):
                best_value, psnr = v.scan(axis, values)
                scans[NAMES[axis]] = [round(float(np.degrees(best_value * 1e-3)) if axis < 3 else best_value, 3),
                                      round(psnr - before, 2)]
            row["axis_scan_best_and_gain_db"] = scans
            line += "; axis alone (best, dB gained): " + ", ".join(f"{n} {b:+g} {g:+.2f}"
                                                                     for n, (b, g) in scans.items())
        rows.append(row)
        c = row["aligned_6dof"]
        print(f"  {kind:5s} frame {row['frame']:2d}: {before:.2f} dB (tiles {tile_before:.2f}) -> 6-DoF "
              f"{after:.2f} (tiles {tile_after:.2f}); pitch {c['pitch_deg']:+.3f} yaw {c['yaw_deg']:+.3f} roll "
              f"{c['roll_deg']:+.3f} deg, lateral {c['lateral_cm']:+.1f} down {c['down_cm']:+.1f} along "
              f"{c['along_cm']:+.1f} cm" + line + f" ({time.perf_counter() - started:.0f} s)", flush=True)
    out = {"psnr_db": round(m["psnr_db"], 2), "psnr_train_db": round(m["psnr_train_db"], 2), "views": rows}
    for kind in ("held", "train"):
        sel = [r for r in rows if r["kind"] == kind]
        if not sel:
            continue
        summary = {k: round(float(np.mean([r[k] for r in sel])), 2)
                   for k in ("psnr_db", "tile_psnr_db", "psnr_6dof_db", "tile_psnr_6dof_db", "psnr_searched_db",
                             "tile_psnr_searched_db")}
        for name in NAMES:
            vals = np.array([r["aligned_6dof"][name] for r in sel])
            summary[f"{name}_mean"] = round(float(vals.mean()), 3)
            summary[f"{name}_rms"] = round(float(np.sqrt((vals ** 2).mean())), 3)
        gain = summary["tile_psnr_db"] - summary["psnr_db"]
        rigid = summary["psnr_searched_db"] - summary["psnr_db"]  # the bounded search (L-BFGS can slide off)
        summary["share_of_tile_gain_recovered"] = round(rigid / gain, 2) if gain > 0 else None
        for name in NAMES:
            vals = np.array([r["searched"][name] for r in sel])
            summary[f"searched_{name}_rms"] = round(float(np.sqrt((vals ** 2).mean())), 3)
        out[kind] = summary
        print(f"  {kind}: mean {summary['psnr_db']:.2f} dB -> aligned {summary['psnr_6dof_db']:.2f}, searched "
              f"{summary['psnr_searched_db']:.2f}; tiles "
              f"{summary['tile_psnr_db']:.2f} -> {summary['tile_psnr_6dof_db']:.2f}; rigid share of the tile gain "
              f"{summary['share_of_tile_gain_recovered']}; RMS " + ", ".join(
                  f"{n} {summary[n + '_rms']}" for n in NAMES) + "; searched RMS " + ", ".join(
                  f"{n} {summary['searched_' + n + '_rms']}" for n in NAMES), flush=True)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="held-out + every 4th training view, gap 1 only")
    parser.add_argument("--refined", action="store_true", help="also map with pose refinement on")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-map", action="store_true", help="the map-independent checks only")
    parser.add_argument("--tiles", action="store_true", help="only the tile shifts' pattern by distance band")
    parser.add_argument("--corrections", help="a JSON line this script printed: check its corrections only")
    args = parser.parse_args()
    if args.corrections:
        done = json.loads(Path(args.corrections).read_text().strip().splitlines()[-1])
        print(json.dumps(epipolar_of_corrections(done["recorded"]["views"])))
        return 0
    if args.tiles:
        with tempfile.TemporaryDirectory() as tmp:
            log = Path(tmp) / "kitti_odometry_01.mcap"
            subprocess.run([ROADLOG, "import", "kitti-odometry", str(FOLDER), "--out", str(log)], check=True,
                           capture_output=True)
            config, config_path = config_from_logs([str(log)])
            config = with_seed(config, args.seed)
            result, drive, _ = mapped_once(log, config, config_path)
            selected = select_keyframes(drive.keyframes, drive.path, config.mapper.inputs.keyframe_spacing_m)
            held = [k for i, k in enumerate(selected) if i % HOLDOUT_EVERY == HOLDOUT_EVERY // 2]
            train = [k for i, k in enumerate(selected) if i % HOLDOUT_EVERY != HOLDOUT_EVERY // 2]
            out = {"held": tiles_report(result.road_map, drive, config, held, "held-out"),
                   "train": tiles_report(result.road_map, drive, config, train[::3], "train")}
        print(json.dumps(out))
        return 0
    out = {"epipolar": epipolar((1,) if args.quick else (1, 2))}
    if not args.skip_map:
        with tempfile.TemporaryDirectory() as tmp:
            log = Path(tmp) / "kitti_odometry_01.mcap"
            subprocess.run([ROADLOG, "import", "kitti-odometry", str(FOLDER), "--out", str(log)], check=True,
                           capture_output=True)
            out["recorded"] = map_alignment(log, args.seed, args.quick, False)
            print("the map-fitted corrections against the raw frames' epipolar geometry:")
            out["corrections_vs_epipolar"] = epipolar_of_corrections(out["recorded"]["views"])
            if args.refined:
                out["refined"] = map_alignment(log, args.seed, args.quick, True)
    for gap in list(out["epipolar"]):
        if gap.startswith("gap_"):
            out["epipolar"][gap].pop("per_pair")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
