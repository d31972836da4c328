"""The live mapping worker: `python -m mapping.mapping_worker --config PATH [--output-dir DIR]`.

A bus thread subscribes (lossless) to the cameras, masks, Lidar, GNSS, IMU, wheel speeds and time
anchors and appends everything to the disk spool (`mapping.keyframe_spool`; Lidar every n-th scan);
GNSS/IMU/wheels/anchors are also kept in memory from the oldest unfinished window on. The main thread
fuses the trajectory so far about once a second (`drive_inputs.fuse_log_trajectory`) to know the
distance travelled, and as soon as `window_after_m` of road lie beyond a window centre it optimises
that window ([centre - window_before_m, centre + window_after_m]; centres every half window, so the
windows overlap by half) with `reconstruction.reconstruct` on the window's keyframes, trajectory and
Lidar ground points. Each window's BEV goes into the disk tiles (`mapping.map_tiles`), the latest
previews into `<data>/map/previews`, and a line into the journal `<data>/map/journal.json` with its
provenance (host time range, per-topic seq ranges, log segments named by recorder/replay health, the
config's path and hash). On SIGTERM/SIGINT the worker drains the bus, finishes the remaining windows
(the last one shorter), writes the final map under `<data>/map/final` and exits 0. Killed, it resumes
from the journal, tiles and spool on its next start. A failed window is counted, reported and retried;
after its last attempt it is recorded as failed in the journal and the worker moves on.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import resource
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from daemon import bus
from daemon.config import CarConfig, ConfigError, data_dir, load_config, resolve_path
from daemon.health import HealthCounters
from daemon.status_server import preview_dir
from daemon.topics import (
    GNSS_FIX,
    IMU,
    LIDAR_PACKETS,
    TIME_ANCHOR,
    WHEEL_SPEEDS,
    camera_topic,
    health_topic,
    mask_topic,
    topic_table,
)
from drivers.lidar.ouster_metadata import parse_metadata
from mapping import map_tiles
from mapping.drive_inputs import (
    camera_models,
    camera_pose,
    decode_image,
    decode_mask,
    fuse_log_trajectory,
    lidar_ground_from_packets,
)
from mapping.keyframe_spool import KeyframeSpool
from mapping.lidar_ground import GroundFilter
from mapping.local_frame import LocalFrame
from mapping.map_export import bev_rasters, elevation_image
from mapping.reconstruction import reconstruct
from mapping.road_map import NO_LABEL
from mapping.scene_data import Keyframe
from mapping.scene_data import Trajectory as PathTrajectory
from mapping.semantic_classes import CLASS_COLOURS
from mapping.sensor_time import ClockMap, fit_clock
from mapping.trajectory import Trajectory

PROCESS = "mapper"
FUSION_MARGIN_S = 20.0  # data kept (and fused) before the oldest unfinished window starts
FUSION_PERIOD_S = 1.0
FREE_CLOCK_RATE_FIT_MIN_S = 600.0  # shorter spans: a free-running clock is taken at rate 1
TILE_M = 40.0
LIDAR_EVERY_N_SCANS = 2
WINDOW_ATTEMPTS = 2
DRAIN_QUIET_S = 1.0  # at shutdown: the bus counts as drained after this long without a message
SMALL_TOPICS = (GNSS_FIX, IMU, WHEEL_SPEEDS, TIME_ANCHOR)
SEGMENT_SOURCES = (health_topic("recorder"), health_topic("replay"))
log = logging.getLogger(__name__)


def window_span(index: int, before_m: float, after_m: float) -> tuple[float, float, float]:
    """(centre, start, end) in metres along the drive of window `index` (centres every half window)."""
    centre = index * (before_m + after_m) / 2.0
    return centre, max(0.0, centre - before_m), centre + after_m


def windows_for_drive(total_m: float, before_m: float, after_m: float) -> int:
    """How many windows a finished drive of `total_m` needs: every centre whose central stretch has road."""
    half = (before_m + after_m) / 4.0
    k = 0
    while window_span(k, before_m, after_m)[0] - half < total_m:
        k += 1
    return max(k, 1)


@dataclass
class Odometry:
    """Distance along the drive at host times: knots every half second, extended by each fusion."""

    knots_t: list[int] = field(default_factory=list)
    knots_s: list[float] = field(default_factory=list)

    def extend(self, trajectory: Trajectory, junction_ns: int) -> None:
        """Replace the knots after `junction_ns` by the trajectory's, continuous at the junction."""
        t = trajectory.times_ns
        latest = self.knots_t[-1] if self.knots_t else int(t[-1])  # never skip past what is known
        junction = max(int(t[0]), min(junction_ns, int(t[-1]), latest))
        keep = [i for i, kt in enumerate(self.knots_t) if kt <= junction]
        if keep and self.knots_t[keep[-1]] >= t[0]:
            j = keep[-1]
            base_t, base_s = self.knots_t[j], self.knots_s[j]
        elif not self.knots_t:
            base_t, base_s = int(t[0]), 0.0
        else:  # the fusion starts after the last knot (a gap): continue from the last knot
            base_t, base_s = int(t[0]), self.knots_s[keep[-1]] if keep else self.knots_s[-1]
            keep = keep or list(range(len(self.knots_t)))
        self.knots_t = [self.knots_t[i] for i in keep]
        self.knots_s = [self.knots_s[i] for i in keep]
        if not self.knots_t or self.knots_t[-1] != base_t:
            self.knots_t.append(base_t)
            self.knots_s.append(base_s)
        s0 = float(trajectory.distance_at(base_t)[0])
        new_t = np.arange(base_t + 500_000_000, int(t[-1]), 500_000_000, dtype=np.int64).tolist() + [int(t[-1])]
        new_t = [x for x in new_t if x > base_t]
        if new_t:
            s = trajectory.distance_at(np.array(new_t, np.int64)) - s0 + base_s
            self.knots_t += new_t
            self.knots_s += [float(v) for v in s]

    @property
    def distance_m(self) -> float:
        return self.knots_s[-1] if self.knots_s else 0.0

    def time_at(self, s: float) -> int:
        """First host time at which the drive reached distance s (clamped to the known span)."""
        arr = np.asarray(self.knots_s)
        i = int(np.searchsorted(arr, s, side="left"))
        if i <= 0:
            return self.knots_t[0]
        if i >= len(arr):
            return self.knots_t[-1]
        span = arr[i] - arr[i - 1]
        f = 0.0 if span <= 0 else (s - arr[i - 1]) / span
        return int(self.knots_t[i - 1] + f * (self.knots_t[i] - self.knots_t[i - 1]))


def span_clock(stamps_ns: list[int], host_ns: list[int], anchors: list[tuple[int, int]]) -> ClockMap:
    """`fit_clock` for the few seconds or minutes the worker holds: a free-running clock keeps rate 1.

    Over a short span the fitted rate of a free-running clock is arrival jitter, not drift (a crystal
    drifts < 100 ppm: 6 ms a minute), and a rate error stretches that sensor's time axis, so wheel
    speeds integrate to a wrong distance. The offset is refitted with rate 1 (shortest latency)."""
    clock = fit_clock(stamps_ns, host_ns, anchors)
    if clock.kind != "free" or len(stamps_ns) == 0:
        return clock
    stamps, host = np.asarray(stamps_ns, np.int64), np.asarray(host_ns, np.int64)
    if (stamps.max() - stamps.min()) > FREE_CLOCK_RATE_FIT_MIN_S * 1e9:
        return clock
    offset = float(np.min(host - host[0] - (stamps - stamps[0]))) + float(host[0])
    return ClockMap("free", 1.0, offset, int(stamps[0]))


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _atomic_png(path: Path, rgb: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", cv2.cvtColor(np.flipud(rgb), cv2.COLOR_RGB2BGR))  # north up
    if not ok:
        raise ValueError(f"cannot encode {path.name}")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data.tobytes())
    os.replace(tmp, path)


def semantic_image(labels: np.ndarray) -> np.ndarray:
    return CLASS_COLOURS[np.minimum(labels, len(CLASS_COLOURS) - 1)] * (labels != NO_LABEL)[..., None].astype(np.uint8)


class BusReader(threading.Thread):
    """Reads every topic the mapper needs into the spool (and the small streams into memory)."""

    def __init__(self, config: CarConfig, spool: KeyframeSpool, lock: threading.Lock, health: HealthCounters,
                 last_seq: dict[str, int], packets_per_scan: int):
        super().__init__(name="mapper-bus", daemon=True)
        self.config = config
        self.spool = spool
        self.lock = lock
        self.health = health
        self.last_seq = last_seq
        self.small: dict[str, list] = {t: [] for t in SMALL_TOPICS}
        self.segments: dict[str, list[int]] = {}  # segment name -> [first, last] host ns seen open
        self.stop_requested = threading.Event()
        self.drained = threading.Event()
        cams = [c.name for c in config.sensors.cameras]
        table = topic_table(config)
        self.topics = [t for t in [camera_topic(c) for c in cams] + [mask_topic(c) for c in cams]
                       + [LIDAR_PACKETS, GNSS_FIX, IMU, WHEEL_SPEEDS, TIME_ANCHOR] if t in table]
        self.subs: dict[str, bus.Subscriber] = {}
        self.side: dict[str, bus.Subscriber] = {}
        self.lidar_count = 0
        self.packets_per_scan = packets_per_scan
        self.last_message_ns = time.monotonic_ns()
        self.lost = 0

    def attach(self) -> None:
        """Subscribe to every topic whose ring exists (again later for the others)."""
        for topic in self.topics:
            if topic not in self.subs:
                try:
                    self.subs[topic] = bus.open_subscriber(self.config, topic, start="oldest", lossless=True)
                except FileNotFoundError:
                    pass
        for topic in SEGMENT_SOURCES:
            if topic not in self.side:
                try:
                    self.side[topic] = bus.open_subscriber(self.config, topic, start="oldest")
                except FileNotFoundError:
                    pass

    def _take(self, topic: str, msg: object) -> None:
        if msg.seq <= self.last_seq.get(topic, -1):
            return  # spooled before a restart
        self.last_seq[topic] = msg.seq
        self.health.received += 1
        arrival = msg.host_mono_ns
        if topic == LIDAR_PACKETS:
            n = self.lidar_count
            self.lidar_count += 1
            if (n // self.packets_per_scan) % LIDAR_EVERY_N_SCANS:
                return
        with self.lock:
            self.spool.append(topic, msg, arrival)
            if topic in self.small:
                self.small[topic].append(msg)

    def _side(self, topic: str, msg: object) -> None:
        try:
            detail = json.loads(msg.detail or "{}")
        except json.JSONDecodeError:
            return
        names = [detail.get("segment")] if isinstance(detail.get("segment"), str) else []
        names += [str(p) for p in detail.get("files", []) if isinstance(p, str)]
        for name in names:
            span = self.segments.setdefault(name, [msg.host_mono_ns, msg.host_mono_ns])
            span[1] = msg.host_mono_ns

    def run(self) -> None:
        next_attach = 0.0
        while True:
            if time.monotonic() >= next_attach:
                self.attach()
                next_attach = time.monotonic() + 0.5
            got = 0
            for topic, sub in self.subs.items():
                for _ in range(64):
                    msg = sub.read(0, copy=True)
                    if msg is None:
                        break
                    got += 1
                    self._take(topic, msg)
            for topic, sub in self.side.items():
                msg = sub.read(0, copy=True)
                while msg is not None:
                    self._side(topic, msg)
                    msg = sub.read(0, copy=True)
            self.lost = sum(s.lost for s in self.subs.values())
            now = time.monotonic_ns()
            if got:
                self.last_message_ns = now
                with self.lock:
                    self.spool.flush()
            elif self.stop_requested.is_set() and now - self.last_message_ns > DRAIN_QUIET_S * 1e9:
                break
            else:
                time.sleep(0.01)
        with self.lock:
            self.spool.flush_close()
        for sub in list(self.subs.values()) + list(self.side.values()):
            sub.close()
        self.drained.set()

    def prune(self, before_ns: int) -> None:
        with self.lock:
            for topic, msgs in self.small.items():
                if topic != TIME_ANCHOR:
                    self.small[topic] = [m for m in msgs if m.host_mono_ns >= before_ns]
            self.spool.prune_before(before_ns)

    def small_copy(self) -> dict[str, list]:
        with self.lock:
            return {t: list(v) for t, v in self.small.items()}


@dataclass
class WorkerState:
    """What /status and the journal show of the worker's progress."""

    windows_done: int = 0
    windows_failed: int = 0
    windows_pending: int = 0
    distance_m: float = 0.0
    mapped_until_m: float = 0.0
    lag_s: float = 0.0
    last_window_wall_s: float = 0.0
    errors: int = 0
    last_error: str = ""
    finished: bool = False


class MappingWorker:
    def __init__(self, config: CarConfig, config_path: str, output_dir: str | None = None):
        self.config = config
        self.config_path = str(Path(config_path).resolve())
        self.config_sha256 = hashlib.sha256(Path(config_path).read_bytes()).hexdigest()
        self.mapper = config.mapper
        self.folder = data_dir(config, config_path, output_dir) / "map"
        self._archive_finished_map()
        self.tiles_dir = self.folder / "tiles"
        self.previews = preview_dir(self.folder.parent)
        for d in (self.folder, self.tiles_dir, self.previews):
            d.mkdir(parents=True, exist_ok=True)
        self.cameras = camera_models(config)
        self.cam_names = sorted(self.cameras)
        self.res = self.mapper.mesh_side_m
        self.tile_cells = max(1, int(round(TILE_M / self.res)))
        self.health = HealthCounters(PROCESS)
        self.state = WorkerState()
        self.lock = threading.Lock()
        self.spool = KeyframeSpool(self.folder / "spool", topic_table(config), chunk_s=2.0)
        self.journal_path = self.folder / "journal.json"
        self.journal = self._load_journal()
        self.odometry = Odometry(list(self.journal.get("odometry_t", [])), list(self.journal.get("odometry_s", [])))
        self.origin = LocalFrame(*self.journal["origin"]) if self.journal.get("origin") else None
        self.lidar_meta = (parse_metadata(resolve_path(config_path, config.sensors.lidar.metadata_file))
                           if config.sensors.lidar is not None else None)
        last_seq = self._restore_from_spool()
        self.reader = BusReader(config, self.spool, self.lock, self.health, last_seq,
                                self.lidar_meta.packets_per_frame if self.lidar_meta else 1)
        self._refill_small()
        self.trajectory: Trajectory | None = None
        self.state.windows_done = sum(1 for w in self.journal["windows"] if w["status"] == "done")
        self.state.windows_failed = sum(1 for w in self.journal["windows"] if w["status"] == "failed")
        self.state.mapped_until_m = self.journal.get("mapped_until_m", 0.0)

    # ---- persistence -------------------------------------------------------------------------------------
    def _archive_finished_map(self) -> None:
        journal = self.folder / "journal.json"
        if journal.exists() and json.loads(journal.read_text()).get("finished"):
            shutil.move(str(self.folder), str(self.folder.with_name(f"map-{time.strftime('%Y%m%d-%H%M%S')}")))

    def _load_journal(self) -> dict:
        if self.journal_path.exists():
            return json.loads(self.journal_path.read_text())
        return {"version": 1, "config_path": self.config_path, "config_sha256": self.config_sha256,
                "grid_resolution_m": self.res, "tile_cells": self.tile_cells, "cameras": self.cam_names,
                "windows": [], "next_window": 0, "finished": False}

    def _save_journal(self) -> None:
        self.journal.update(odometry_t=self.odometry.knots_t, odometry_s=self.odometry.knots_s,
                            mapped_until_m=self.state.mapped_until_m,
                            origin=None if self.origin is None else [self.origin.lat_deg, self.origin.lon_deg,
                                                                     self.origin.alt_m])
        _atomic_write_text(self.journal_path, json.dumps(self.journal, indent=1))

    def _restore_from_spool(self) -> dict[str, int]:
        """Last seq per topic already spooled (a restart skips those when the bus still holds them)."""
        last: dict[str, int] = {}
        for chunk in self.spool.chunks:
            for _, topic, msg in self.spool.read(chunk.first_ns, chunk.last_ns, set(self.spool.topics)):
                last[topic] = max(last.get(topic, -1), msg.seq)
        return last

    def _refill_small(self) -> None:
        if not self.spool.chunks:
            return
        for _, topic, msg in self.spool.read(self.spool.chunks[0].first_ns, self.spool.chunks[-1].last_ns,
                                             set(SMALL_TOPICS)):
            self.reader.small[topic].append(msg)

    # ---- trajectory --------------------------------------------------------------------------------------
    def _fuse(self, small: dict[str, list], until_ns: int | None = None) -> Trajectory | None:
        gnss, imu, wheels = small[GNSS_FIX], small[IMU], small[WHEEL_SPEEDS]
        if until_ns is not None:
            gnss, imu, wheels = ([m for m in x if m.host_mono_ns <= until_ns] for x in (gnss, imu, wheels))
        if len(gnss) < 5 or len(imu) < 20 or len(wheels) < 10:
            return None
        anchors = [(m.host_mono_ns, m.utc_ns) for m in small[TIME_ANCHOR]]
        clocks = {t: span_clock([m.sensor_time_ns for m in small[t]], [m.host_mono_ns for m in small[t]], anchors)
                  for t in (GNSS_FIX, IMU, WHEEL_SPEEDS)}
        if self.origin is None:
            g = min(gnss, key=lambda m: m.sensor_time_ns)
            self.origin = LocalFrame(g.latitude_deg, g.longitude_deg, g.altitude_m)
        return fuse_log_trajectory(gnss, imu, wheels, self.config, self.origin, clocks)

    def update_distance(self) -> None:
        try:
            traj = self._fuse(self.reader.small_copy())
        except Exception as exc:  # a fusion failure is reported, and retried with more data
            self._error(f"pose fusion: {exc}")
            return
        if traj is None:
            return
        self.trajectory = traj
        junction = int(traj.times_ns[0] + FUSION_MARGIN_S * 1e9 / 2)
        self.odometry.extend(traj, junction)
        self.state.distance_m = self.odometry.distance_m
        mapped_t = self.odometry.time_at(self.state.mapped_until_m) if self.odometry.knots_t else 0
        self.state.lag_s = max(0.0, (self.odometry.knots_t[-1] - mapped_t) / 1e9) if mapped_t else 0.0

    # ---- windows -----------------------------------------------------------------------------------------
    def _window_ready(self, k: int, end_of_drive: bool) -> bool:
        _, _, s_hi = window_span(k, self.mapper.window_before_m, self.mapper.window_after_m)
        if end_of_drive:
            return k < windows_for_drive(self.state.distance_m, self.mapper.window_before_m,
                                         self.mapper.window_after_m)
        return bool(self.odometry.knots_s) and self.state.distance_m >= s_hi

    def _window_inputs(self, k: int) -> tuple:
        m = self.mapper
        centre, s_lo, s_hi = window_span(k, m.window_before_m, m.window_after_m)
        s_hi = min(s_hi, self.state.distance_m)
        t_lo, t_hi = self.odometry.time_at(s_lo), self.odometry.time_at(s_hi)
        small = self.reader.small_copy()
        traj = self._fuse(small, until_ns=t_hi + 2_000_000_000)
        if traj is None:
            raise ValueError("not enough GNSS/IMU/wheel data for the window")
        t_lo, t_hi = max(t_lo, int(traj.times_ns[0])), min(t_hi, int(traj.times_ns[-1]))
        if t_hi - t_lo < 1e8:
            raise ValueError(f"window {k}: trajectory covers only [{traj.times_ns[0]}, {traj.times_ns[-1]}]")
        cams = [c.name for c in self.config.sensors.cameras]
        want = {camera_topic(c) for c in cams} | {mask_topic(c) for c in cams}
        if self.lidar_meta is not None:
            want.add(LIDAR_PACKETS)
        with self.lock:
            records = list(self.spool.read(t_lo - 1_000_000_000, t_hi + 1_000_000_000, want))
        anchors = [(a.host_mono_ns, a.utc_ns) for a in small[TIME_ANCHOR]]
        by_topic: dict[str, list] = {}
        for _, topic, msg in records:
            by_topic.setdefault(topic, []).append(msg)
        clocks = {t: span_clock([m.sensor_time_ns for m in v], [m.host_mono_ns for m in v], anchors)
                  for t, v in by_topic.items()}
        # the window's trajectory: poses within [t_lo, t_hi], seconds from t_lo
        inside = (traj.times_ns > t_lo) & (traj.times_ns < t_hi)
        times = np.concatenate([[t_lo], traj.times_ns[inside], [t_hi]]).astype(np.int64)
        pos, _ = traj.interpolate(times)
        path = PathTrajectory((times - t_lo) / 1e9, pos)
        keyframes = []
        spacing = m.keyframe_spacing_m
        for cam in self.config.sensors.cameras:
            masks = {x.sensor_time_ns: x for x in by_topic.get(mask_topic(cam.name), [])}
            frames = sorted(by_topic.get(camera_topic(cam.name), []), key=lambda f: f.sensor_time_ns)
            if not frames:
                continue
            host = clocks[camera_topic(cam.name)].to_host([f.sensor_time_ns for f in frames])
            last_s = -np.inf
            for f, t in zip(frames, host, strict=True):
                if not t_lo <= t <= t_hi or f.sensor_time_ns not in masks:
                    continue
                s = float(traj.distance_at(int(t))[0])
                if s - last_s < spacing:
                    continue
                last_s = s
                keyframes.append(Keyframe(cam.name, (int(t) - t_lo) / 1e9,
                                          camera_pose(traj, int(t), cam.extrinsics.matrix()), decode_image(f),
                                          decode_mask(masks[f.sensor_time_ns])))
        keyframes.sort(key=lambda kf: kf.timestamp)
        ground = None
        packets = by_topic.get(LIDAR_PACKETS, [])
        if packets:
            ground = lidar_ground_from_packets(packets, clocks[LIDAR_PACKETS], self.lidar_meta, self.config, traj, 1,
                                               GroundFilter(corridor_half_width_m=m.corridor_half_width_m))
        fed = dict(by_topic)
        for t in (GNSS_FIX, IMU, WHEEL_SPEEDS):
            fed[t] = [x for x in small[t] if t_lo <= x.host_mono_ns <= t_hi]
        seq = {t: [min(x.seq for x in v), max(x.seq for x in v)] for t, v in sorted(fed.items()) if v}
        provenance = {"host_time_ns": [t_lo, t_hi], "seq": seq,
                      "segments": sorted(n for n, (a, b) in self.reader.segments.items() if a <= t_hi and b >= t_lo),
                      "keyframes": len(keyframes), "lidar_packets": len(packets),
                      "lidar_ground_points": 0 if ground is None else len(ground)}
        return centre, s_lo, s_hi, t_lo, t_hi, traj, path, keyframes, ground, provenance

    def run_window(self, k: int) -> dict:
        started = time.perf_counter()
        m = self.mapper
        centre, s_lo, s_hi, t_lo, t_hi, traj, path, keyframes, ground, provenance = self._window_inputs(k)
        if not keyframes:
            raise ValueError(f"window {k}: no keyframes in [{s_lo:.1f}, {s_hi:.1f}] m")
        seed = m.seed * 1_000_003 + k
        np.random.seed(seed % 2**32)
        torch.manual_seed(seed)
        cfg = m.model_copy(update={"seed": seed})
        result = reconstruct(keyframes, self.cameras, path, ground, cfg, self.config.vehicle.reference_height_m,
                             holdout_every=0, progress=False)
        bev = bev_rasters(result.road_map, self.cam_names, self.res)
        j0, i0 = (int(round(v / self.res)) for v in bev["origin_xy"])
        half = (m.window_before_m + m.window_after_m) / 4.0
        c_lo = -np.inf if k == 0 else (self.odometry.time_at(centre - half) - t_lo) / 1e9
        c_hi = (self.odometry.time_at(centre + half) - t_lo) / 1e9
        h, w = bev["elevation"].shape
        central = np.zeros((h, w), bool)
        seen = np.isfinite(bev["elevation"])
        if seen.any():
            ii, jj = np.nonzero(seen)
            xy = np.stack([(j0 + jj) * self.res, (i0 + ii) * self.res], 1)
            _, nearest = cKDTree(path.positions[:, :2]).query(xy)
            t = path.times[nearest]
            central[ii, jj] = (t >= c_lo) & (t < c_hi)
        raster = map_tiles.WindowRaster(i0, j0, bev["elevation"], bev["labels"], bev["rgb"], central)
        tiles = map_tiles.write_window(self.tiles_dir, self.tile_cells, k, raster, self.cam_names)
        self._write_previews(bev)
        wall = time.perf_counter() - started
        keep = ("psnr_train_db", "elev_error_cm", "miou_pct", "steps", "vertices", "vertices_observed",
                "optimise_wall_s", "loss_last")
        extent = ([float(x) for x in path.positions[:, :2].min(0)] + [float(x) for x in path.positions[:, :2].max(0)])
        return {"index": k, "status": "done", "centre_m": centre, "start_m": s_lo, "end_m": s_hi, "seed": seed,
                "wall_s": wall, "finished_mono_ns": time.monotonic_ns(), "tiles": tiles, "trajectory_xy_box": extent,
                "metrics": {x: result.metrics.get(x) for x in keep}, **provenance,
                "config": {"path": self.config_path, "sha256": self.config_sha256}}

    def _write_previews(self, bev: dict) -> None:
        _atomic_png(self.previews / "rgb.png", bev["rgb"][self.cam_names[0]])
        _atomic_png(self.previews / "semantics.png", semantic_image(bev["labels"]))
        _atomic_png(self.previews / "elevation.png", elevation_image(bev["elevation"]))

    def _error(self, what: str) -> None:
        self.state.errors += 1
        self.state.last_error = what
        self.health.count_error(what)
        log.error("%s", what)

    def step(self, end_of_drive: bool) -> bool:
        """Optimise the next window if it is ready; False when there is nothing to do now."""
        k = self.journal["next_window"]
        if not self._window_ready(k, end_of_drive):
            return False
        attempts = 0
        while True:
            attempts += 1
            try:
                entry = self.run_window(k)
                break
            except Exception as exc:  # counted, reported, retried, then recorded as failed
                self._error(f"window {k} attempt {attempts}: {type(exc).__name__}: {exc}")
                if attempts >= WINDOW_ATTEMPTS:
                    centre, s_lo, s_hi = window_span(k, self.mapper.window_before_m, self.mapper.window_after_m)
                    entry = {"index": k, "status": "failed", "centre_m": centre, "start_m": s_lo, "end_m": s_hi,
                             "error": self.state.last_error, "finished_mono_ns": time.monotonic_ns()}
                    self.state.windows_failed += 1
                    break
        entry["attempts"] = attempts
        self.journal["windows"].append(entry)
        self.journal["next_window"] = k + 1
        if entry["status"] == "done":
            self.state.windows_done += 1
            self.state.last_window_wall_s = entry["wall_s"]
        self.state.mapped_until_m = max(self.state.mapped_until_m, min(entry["end_m"], self.state.distance_m))
        self._save_journal()
        _, next_lo, _ = window_span(k + 1, self.mapper.window_before_m, self.mapper.window_after_m)
        self.reader.prune(self.odometry.time_at(next_lo) - int(FUSION_MARGIN_S * 1e9))
        return True

    # ---- health ------------------------------------------------------------------------------------------
    def health_message(self):
        st = self.state
        m = self.mapper
        ready = 0
        k = self.journal["next_window"]
        while window_span(k + ready, m.window_before_m, m.window_after_m)[2] <= st.distance_m:
            ready += 1
        st.windows_pending = ready
        msg = self.health.snapshot()
        msg.state = "degraded" if st.errors else "ok"
        msg.errors = st.errors
        msg.dropped = self.reader.lost
        msg.detail = json.dumps({
            "windows_done": st.windows_done, "windows_failed": st.windows_failed, "windows_pending": ready,
            "distance_m": round(st.distance_m, 2), "mapped_until_m": round(st.mapped_until_m, 2),
            "lag_m": round(max(0.0, st.distance_m - st.mapped_until_m), 2), "lag_s": round(st.lag_s, 2),
            "last_window_wall_s": round(st.last_window_wall_s, 2), "spool_bytes": self.spool.bytes,
            "errors": st.errors, "last_error": st.last_error, "bus_lost": self.reader.lost,
            "finished": st.finished,
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        })
        return msg

    # ---- final map ---------------------------------------------------------------------------------------
    def write_final_map(self) -> Path:
        out = self.folder / "final"
        out.mkdir(parents=True, exist_ok=True)
        meta = {"windows": self.journal["windows"], "config": {"path": self.config_path,
                                                                "sha256": self.config_sha256},
                "distance_m": self.state.distance_m, "origin_lat_lon_alt": self.journal.get("origin")}
        if map_tiles.tile_indices(self.tiles_dir):
            mos = map_tiles.mosaic(self.tiles_dir, self.tile_cells, self.res, self.cam_names)
            for c in self.cam_names:
                _atomic_png(out / f"bev_rgb_{c}.png", mos.rgb[c])
            _atomic_png(out / "bev_semantics.png", semantic_image(mos.labels))
            _atomic_png(out / "bev_elevation.png", elevation_image(mos.elevation))
            np.save(out / "bev_elevation.npy", mos.elevation)
            np.save(out / "bev_semantics.npy", mos.labels)
            meta.update(origin_xy=mos.origin_xy, resolution_m=mos.resolution_m, shape=list(mos.elevation.shape),
                        cell="cell (i, j) of the .npy rasters is centred at (x0 + j*res, y0 + i*res); "
                             "PNGs are flipped north-up", semantics_no_label=NO_LABEL, cameras=self.cam_names)
            meta["mesh"] = self._write_mesh(mos, out)
        _atomic_write_text(out / "metadata.json", json.dumps(meta, indent=1, default=str))
        return out

    def _write_mesh(self, mos: map_tiles.Mosaic, out: Path, max_vertices: int = 2_000_000) -> dict:
        """A grid mesh of the mosaic (cells as vertices, two triangles per fully mapped 2x2 block)."""
        stride = 1
        while np.isfinite(mos.elevation[::stride, ::stride]).sum() > max_vertices:
            stride += 1
        z = mos.elevation[::stride, ::stride]
        h, w = z.shape
        valid = np.isfinite(z)
        index = np.full((h, w), -1, np.int64)
        index[valid] = np.arange(valid.sum())
        ii, jj = np.nonzero(valid)
        res = mos.resolution_m * stride
        vertices = np.stack([mos.origin_xy[0] + jj * res, mos.origin_xy[1] + ii * res, z[valid]], 1)
        a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
        full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
        faces = np.concatenate([np.stack([a[full], b[full], d[full]], 1), np.stack([a[full], d[full], c[full]], 1)])
        colours = mos.rgb[self.cam_names[0]][::stride, ::stride][valid]
        mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colours, process=False)
        for name in ("mesh.ply", "mesh.glb"):
            mesh.export(out / name)
        return {"files": ["mesh.ply", "mesh.glb"], "vertices": len(vertices), "faces": len(faces),
                "resolution_m": res}

    # ---- main loop ---------------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> int:
        torch.set_num_threads(self.mapper.threads)
        pub = bus.open_publisher(self.config, health_topic(PROCESS))
        health_stop = threading.Event()

        def publish_health() -> None:
            while not health_stop.wait(1.0):
                pub.publish(self.health_message())

        health_thread = threading.Thread(target=publish_health, name="mapper-health", daemon=True)
        self.reader.attach()  # registered as a lossless reader before the first health says "up"
        health_thread.start()
        self.reader.start()
        next_fusion = 0.0
        while not stop.is_set():
            if time.monotonic() >= next_fusion:
                self.update_distance()
                next_fusion = time.monotonic() + FUSION_PERIOD_S
            if not self.step(end_of_drive=False):
                stop.wait(0.2)
        log.info("stopping: draining the bus and finishing the remaining windows")
        self.reader.stop_requested.set()
        self.reader.drained.wait()
        self.update_distance()
        while self.step(end_of_drive=True):
            pass
        out = self.write_final_map()
        self.state.finished = True
        self.journal["finished"] = True
        self._save_journal()
        shutil.rmtree(self.spool.folder)  # every window is in the tiles and the final map
        self.spool.chunks = []
        log.info("final map in %s (%d windows done, %d failed)", out, self.state.windows_done,
                 self.state.windows_failed)
        health_stop.set()
        health_thread.join()
        pub.publish(self.health_message())
        pub.close()
        return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapping_worker", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--output-dir", help="data folder (default: recorder.output_dir of the config)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s mapper %(levelname)s %(message)s")
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(exc, file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    return MappingWorker(config, args.config, args.output_dir).run(stop)


if __name__ == "__main__":
    sys.exit(main())
