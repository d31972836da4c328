"""One drive of a fleet job: its id (from its logs' bytes, not their paths), its 160 m windows cut from the inputs
read once (the live worker's schedule, mapping.live.window_schedule), and one window fitted (mapping.fits.
reconstruction, as the live worker fits it) and cut into the tile store's tiles."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from daemon.spine.config import CarConfig
from mapping.fits.reconstruction import reconstruct
from mapping.fleet.geodetic_grid import GridSpec
from mapping.fleet.tile_store import TileStore
from mapping.fleet.window_tiles import window_contributions
from mapping.inputs.drive_inputs import DriveInputs
from mapping.live.window_schedule import window_span, windows_for_drive
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.scene_data import Keyframe, StandingPoints

FAIL_WINDOWS_ENV = "ROADLOG_FLEET_FAIL_WINDOWS"  # fault injection for tests and drills: "NAME:K,..." makes window K
# of the drive whose id or first log's stem is NAME (or any drive: *) raise, every attempt
_ID_BYTES = 1 << 20  # the id reads each log's first and last MiB and its size


def drive_id(logs: list[str | Path]) -> str:
    """12 hex digits naming a drive by its logs' content: the same drive copied elsewhere keeps its id."""
    h = hashlib.sha256()
    for log in logs:
        size = os.path.getsize(log)
        with open(log, "rb") as f:
            h.update(size.to_bytes(8, "little"))
            h.update(f.read(_ID_BYTES))
            f.seek(max(0, size - _ID_BYTES))
            h.update(f.read(_ID_BYTES))
    return h.hexdigest()[:12]


def window_count(path: HorizontalTrack, config: CarConfig) -> int:
    w = config.mapper.windows
    return windows_for_drive(float(path.horizontal_distance()[-1]), w.before_m, w.after_m)


@dataclass
class WindowCut:
    """Window k's share of a drive's inputs; times in seconds from the window's start."""

    index: int
    start_m: float
    end_m: float
    path: HorizontalTrack
    keyframes: list[Keyframe]
    ground: np.ndarray | None
    standing: StandingPoints | None


def cut_window(drive: DriveInputs, k: int, config: CarConfig) -> WindowCut:
    """The keyframes, track, Lidar ground and standing points of window k (by distance along the drive)."""
    m = config.mapper
    path = drive.path
    along = path.horizontal_distance()
    _, s_lo, s_hi = window_span(k, m.windows.before_m, m.windows.after_m)
    s_hi = min(s_hi, float(along[-1]))
    t_lo, t_hi = (float(np.interp(s, along, path.times)) for s in (s_lo, s_hi))
    inside = (path.times > t_lo) & (path.times < t_hi)
    times = np.concatenate([[t_lo], path.times[inside], [t_hi]])
    positions = np.stack([np.interp(times, path.times, path.positions[:, i]) for i in range(3)], 1)
    track = HorizontalTrack(times - t_lo, positions)
    keyframes = [replace(kf, timestamp=kf.timestamp - t_lo) for kf in drive.keyframes if t_lo <= kf.timestamp <= t_hi]
    ground = drive.lidar_ground_points
    if ground is not None and len(ground):
        near = cKDTree(positions[:, :2]).query(ground[:, :2], distance_upper_bound=m.mesh.corridor_half_width_m + 2)[0]
        ground = ground[np.isfinite(near)]
    standing = drive.lidar_standing
    if standing is not None:
        keep = np.flatnonzero((standing.times >= t_lo - 1.0) & (standing.times <= t_hi + 1.0))
        standing = StandingPoints.of([(float(standing.times[i]) - t_lo,
                                       standing.points[standing.starts[i]:standing.starts[i + 1]]) for i in keep])
    return WindowCut(k, s_lo, s_hi, track, keyframes, ground, standing)


def injected_failure(drive: str, stem: str, k: int) -> bool:
    wanted = [item.rsplit(":", 1) for item in os.environ.get(FAIL_WINDOWS_ENV, "").split(",") if ":" in item]
    return any(name in ("*", drive, stem) and index == str(k) for name, index in wanted)


def fit_window(drive: DriveInputs, cut: WindowCut, config: CarConfig, drive_name: str, stem: str,
               store: TileStore, grid: GridSpec) -> dict:
    """Fit window `cut` and write its tile contributions; what it did (the journal's entry, without status)."""
    if injected_failure(drive_name, stem, cut.index):
        raise RuntimeError(f"injected failure ({FAIL_WINDOWS_ENV})")
    if not cut.keyframes:
        raise ValueError(f"window {cut.index}: no keyframes in [{cut.start_m:.1f}, {cut.end_m:.1f}] m")
    m = config.mapper
    seed = m.model.seed * 1_000_003 + cut.index  # as the live worker seeds its windows
    torch.manual_seed(seed)
    cfg = m.model_copy(update={"model": m.model.model_copy(update={"seed": seed})})
    result = reconstruct(cut.keyframes, drive.cameras, cut.path, cut.ground, cfg, config.vehicle.reference_height_m,
                         holdout_every=0, progress=False, lidar_standing=cut.standing)
    cameras = sorted(drive.cameras)
    parts = window_contributions(result.road_map, drive.trajectory.local_frame, drive_name, cut.index, cameras,
                                 grid, m.runtime.raster_threads)
    infos = [store.write(tile, part) for tile, part in parts.items()]
    keep = ("psnr_train_db", "elev_error_cm", "semantics", "vertices", "vertices_observed", "optimise_wall_s")
    return {"start_m": cut.start_m, "end_m": cut.end_m, "keyframes": len(cut.keyframes), "seed": seed,
            "tiles": [i.tile for i in infos], "cells": sum(i.cells for i in infos),
            "metrics": {k: result.metrics.get(k) for k in keep}}
