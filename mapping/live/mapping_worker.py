"""The live mapping worker: `python -m mapping.live.mapping_worker --config PATH [--output-dir DIR]`.

A bus thread subscribes (lossless) to the cameras, masks, Lidar, GNSS, IMU, wheel speeds and time
anchors and appends everything to the disk spool (`mapping.live.keyframe_spool`; Lidar every n-th scan);
GNSS/IMU/wheels/anchors are also kept in memory from the oldest unfinished window on. The main thread
integrates the wheel speeds into the distance travelled (`Odometry`), and as soon as `windows.after_m` of
road lie beyond a window centre and every topic has delivered its data that far (plus the 2 s the
window's inputs reach beyond), it optimises that window ([centre - windows.before_m, centre +
windows.after_m]; centres every half window, so the windows overlap by half) with
`reconstruction.reconstruct` on the window's keyframes, fused trajectory (`drive_inputs.fuse_log_trajectory`)
and Lidar ground points. What a window sees depends on the log's content only, never on arrival timing,
so replaying a log twice gives the same map (tests/test_replay_determinism.py).
Each window's BEV goes into the disk tiles (`mapping.live.map_tiles`), the latest previews into
`<data>/map/previews`, and a line into the journal `<data>/map/journal.jsonl` (`mapping.live.worker_journal`,
append-only) with its provenance (host time range, per-topic seq ranges, log segments named by
recorder/replay health, the config's path and hash). On SIGTERM/SIGINT the worker drains the bus,
finishes the remaining windows (the last one shorter), writes the final map under `<data>/map/final` and
exits 0. Killed, it resumes from the journal, tiles and spool on its next start. A failed window is
counted, reported and retried; after its last attempt it is recorded as failed in the journal and the
worker moves on. With
`mapper.live_view.enabled` each finished window is also published on a Foxglove WebSocket server
(`mapping.live.live_view`).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
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

from daemon.bus import pubsub
from daemon.spine.config import CarConfig, data_dir, load_config, reports_config_errors, resolve_path
from daemon.spine.data_layout import preview_dir
from daemon.spine.health import HealthCounters, process_memory_mb
from daemon.spine.local_frame import LocalFrame
from daemon.spine.semantic_classes import CLASS_COLOURS
from daemon.spine.topics import (
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
from mapping.fits.reconstruction import reconstruct
from mapping.inputs.drive_inputs import (
    camera_models,
    camera_pose,
    decode_image,
    fuse_log_trajectory,
    keyframe_semantics,
    lidar_ground_from_packets,
    segmenter_for,
)
from mapping.inputs.lidar_ground import GroundFilter, keeps_scan
from mapping.live import live_view, map_tiles
from mapping.live.keyframe_spool import KeyframeSpool
from mapping.live.worker_journal import VERSION as JOURNAL_VERSION
from mapping.live.worker_journal import append_line, new_state, progress_line, read_journal
from mapping.localization.keyframe_spacing import spaced_by_distance
from mapping.localization.sensor_time import ClockMap, fit_clock
from mapping.localization.trajectory import HorizontalTrack, Trajectory
from mapping.method.road_map import NO_LABEL
from mapping.method.scene_data import Keyframe
from mapping.outputs.map_export import bev_rasters, elevation_image

PROCESS = "mapper"
FUSION_MARGIN_S = 20.0  # data kept (and fused) before the oldest unfinished window starts
ODOMETRY_PERIOD_S = 1.0
KNOT_NS = 500_000_000
INPUT_HORIZON_NS = 2_000_000_000  # a window's inputs reach this far past its end (fusion; clocks 1 s)
STALLED_TOPIC_NS = 30_000_000_000  # a topic this far behind the newest message is not waited for
FREE_CLOCK_RATE_FIT_MIN_S = 600.0  # shorter spans: a free-running clock is taken at rate 1
TILE_M = 40.0
OVERVIEW_MAX_CELLS = 4_000_000  # the final map's PNGs: an overview, coarser past 4 M cells of bounding box
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
    """Distance along the drive at host times, integrated from the wheel speeds message by message.

    It depends only on the messages, never on when the worker looks at them, so the windows' time
    ranges are the same in every replay of a log (a distance read off successive pose fusions depended
    on how much data each fusion happened to have). Knots at least `KNOT_NS` apart, the newest message
    always the last knot; the integration state is kept so a restart goes on where the journal left off."""

    knots_t: list[int] = field(default_factory=list)
    knots_s: list[float] = field(default_factory=list)
    last_speed_mps: float = 0.0

    def add(self, host_ns: int, speed_mps: float) -> bool:
        """Integrate one wheel-speed message (trapezoids); False for one not after the last."""
        if not self.knots_t:
            self.knots_t, self.knots_s, self.last_speed_mps = [host_ns], [0.0], speed_mps
            return True
        last_t = self.knots_t[-1]
        if host_ns <= last_t:
            return False
        s = self.knots_s[-1] + 0.5 * (speed_mps + self.last_speed_mps) * (host_ns - last_t) / 1e9
        if len(self.knots_t) >= 2 and last_t - self.knots_t[-2] < KNOT_NS:
            self.knots_t[-1], self.knots_s[-1] = host_ns, s  # the tip moves on
        else:
            self.knots_t.append(host_ns)
            self.knots_s.append(s)
        self.last_speed_mps = speed_mps
        return True

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


def wheel_speed_mps(msg: object) -> float | None:
    """The vehicle's speed from one WheelSpeeds message: the mean of the wheels that report one."""
    speeds = [abs(v) for v in (msg.front_left_mps, msg.front_right_mps, msg.rear_left_mps, msg.rear_right_mps)
              if np.isfinite(v)]
    return float(np.mean(speeds)) if speeds else None


def span_clock(stamps_ns: list[int], host_ns: list[int], anchors: list[tuple[int, int]]) -> ClockMap:
    """`fit_clock` for the few seconds or minutes the worker holds, in exact arithmetic where it matters.

    Over a short span the fitted rate of a free-running clock is arrival jitter, not drift (a crystal
    drifts < 100 ppm: 6 ms a minute), and a rate error stretches that sensor's time axis, so wheel
    speeds integrate to a wrong distance. The offset is refitted with rate 1 (shortest latency), in
    integers."""
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
        self.subs: dict[str, pubsub.Subscriber] = {}
        self.side: dict[str, pubsub.Subscriber] = {}
        self.lidar_count = 0
        self.packets_per_scan = packets_per_scan
        self.last_message_ns = time.monotonic_ns()
        self.lost = 0
        self.newest: dict[str, int] = {}  # topic -> newest host time received

    def attach(self) -> None:
        """Subscribe to every topic whose ring exists (again later for the others)."""
        for topic in self.topics:
            if topic not in self.subs:
                try:
                    self.subs[topic] = pubsub.open_subscriber(self.config, topic, start="oldest", lossless=True)
                except FileNotFoundError:
                    pass
        for topic in SEGMENT_SOURCES:
            if topic not in self.side:
                try:
                    self.side[topic] = pubsub.open_subscriber(self.config, topic, start="oldest")
                except FileNotFoundError:
                    pass

    def take(self, topic: str, msg: object) -> None:
        """Spool one message (and keep it in memory if it is a small stream)."""
        if msg.seq <= self.last_seq.get(topic, -1):
            return  # spooled before a restart
        self.last_seq[topic] = msg.seq
        self.health.received += 1
        arrival = msg.host_mono_ns
        self.newest[topic] = max(arrival, self.newest.get(topic, arrival))
        if topic == LIDAR_PACKETS:
            n = self.lidar_count
            self.lidar_count += 1
            if not keeps_scan(n, self.packets_per_scan, self.config.mapper.inputs.lidar_every_n_scans):
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
                    self.take(topic, msg)
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

    def complete_until(self, host_ns: int) -> bool:
        """Whether every topic heard from has delivered its messages up to `host_ns` (each topic arrives in
        host-time order); a topic stalled far behind the others is not waited for."""
        newest = dict(self.newest)
        if not newest:
            return False
        top = max(newest.values())
        return all(t >= host_ns or t < top - STALLED_TOPIC_NS for t in newest.values())

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
    wheel_messages_without_speed: int = 0
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
        self.segmenter = segmenter_for(config, config_path)  # None: the masks on the bus
        self.res = self.mapper.mesh.side_m
        self.tile_cells = max(1, int(round(TILE_M / self.res)))
        self.health = HealthCounters(PROCESS)
        self.state = WorkerState()
        self.lock = threading.Lock()
        self.spool = KeyframeSpool(self.folder / "spool", topic_table(config), chunk_s=2.0)
        self.journal = self._load_journal()
        self.odometry_saved = len(self.journal["odometry_t"])  # knots already in the journal
        self.odometry = Odometry(list(self.journal["odometry_t"]), list(self.journal["odometry_s"]),
                                 self.journal["odometry_last_speed_mps"])
        self.origin = LocalFrame(*self.journal["origin"]) if self.journal["origin"] else None
        self.lidar_meta = (parse_metadata(resolve_path(config_path, config.sensors.lidar.metadata_file))
                           if config.sensors.lidar is not None else None)
        last_seq, newest = self._restore_from_spool()
        self.reader = BusReader(config, self.spool, self.lock, self.health, last_seq,
                                self.lidar_meta.packets_per_frame if self.lidar_meta else 1)
        self.reader.newest.update(newest)
        self._refill_small()
        self.state.windows_done = sum(1 for w in self.journal["windows"] if w["status"] == "done")
        self.state.windows_failed = sum(1 for w in self.journal["windows"] if w["status"] == "failed")
        self.state.mapped_until_m = self.journal["mapped_until_m"]
        self.live_view = None
        if self.mapper.live_view.enabled:
            try:
                self.live_view = live_view.start_live_view(self.mapper.live_view)
            except Exception as exc:  # mapping goes on without it
                self._error(f"live view: cannot start: {type(exc).__name__}: {exc}")

    # ---- persistence -------------------------------------------------------------------------------------
    def _archive_finished_map(self) -> None:
        journal = read_journal(self.folder)
        if journal is not None and journal["finished"]:
            shutil.move(str(self.folder), str(self.folder.with_name(f"map-{time.strftime('%Y%m%d-%H%M%S')}")))

    def _load_journal(self) -> dict:
        journal = read_journal(self.folder)
        if journal is None:
            header = {"version": JOURNAL_VERSION, "config_path": self.config_path,
                      "config_sha256": self.config_sha256, "grid_resolution_m": self.res,
                      "tile_cells": self.tile_cells, "cameras": self.cam_names}
            append_line(self.folder, header)
            return new_state(header)
        if journal["skipped_lines"]:
            self._error(f"journal: {journal['skipped_lines']} unreadable line(s) skipped (torn by a crash?)")
        return journal

    def _save_journal(self, window: dict | None = None) -> None:
        """One line: `window` (if any) and the progress since the last line."""
        self.journal.update(odometry_last_speed_mps=self.odometry.last_speed_mps,
                            mapped_until_m=self.state.mapped_until_m,
                            origin=None if self.origin is None else [self.origin.lat_deg, self.origin.lon_deg,
                                                                     self.origin.alt_m])
        append_line(self.folder, progress_line(self.journal, self.odometry.knots_t, self.odometry.knots_s,
                                               self.odometry_saved, window))
        self.odometry_saved = len(self.odometry.knots_t)

    def _restore_from_spool(self) -> tuple[dict[str, int], dict[str, int]]:
        """Last seq and newest host time per topic already spooled (a restart skips those when the bus still
        holds them, and knows how far each topic's data reaches)."""
        last: dict[str, int] = {}
        newest: dict[str, int] = {}
        for chunk in self.spool.chunks:
            for arrival, topic, msg in self.spool.read(chunk.first_ns, chunk.last_ns, set(self.spool.topics)):
                last[topic] = max(last.get(topic, -1), msg.seq)
                newest[topic] = max(newest.get(topic, arrival), arrival)
        return last, newest

    def _refill_small(self) -> None:
        if not self.spool.chunks:
            return
        for _, topic, msg in self.spool.read(self.spool.chunks[0].first_ns, self.spool.chunks[-1].last_ns,
                                             set(SMALL_TOPICS)):
            self.reader.small[topic].append(msg)

    # ---- trajectory --------------------------------------------------------------------------------------
    def _fuse(self, small: dict[str, list], until_ns: int) -> Trajectory | None:
        """The trajectory from the GNSS, IMU and wheel speeds held, up to host time `until_ns`."""
        held = {t: [m for m in small[t] if m.host_mono_ns <= until_ns] for t in SMALL_TOPICS}
        gnss, imu, wheels = held[GNSS_FIX], held[IMU], held[WHEEL_SPEEDS]
        if len(gnss) < 5 or len(imu) < 20 or len(wheels) < 10:
            return None
        anchors = [(m.host_mono_ns, m.utc_ns) for m in held[TIME_ANCHOR]]
        clocks = {t: span_clock([m.sensor_time_ns for m in held[t]], [m.host_mono_ns for m in held[t]], anchors)
                  for t in (GNSS_FIX, IMU, WHEEL_SPEEDS)}
        if self.origin is None:
            g = min(gnss, key=lambda m: m.sensor_time_ns)
            self.origin = LocalFrame(g.latitude_deg, g.longitude_deg, g.altitude_m)
        return fuse_log_trajectory(gnss, imu, wheels, self.config, self.origin, clocks)

    def update_distance(self) -> None:
        """Integrate the wheel speeds that arrived since the last call into the odometry."""
        with self.lock:
            wheels = self.reader.small[WHEEL_SPEEDS]
            last = self.odometry.knots_t[-1] if self.odometry.knots_t else None
            i = len(wheels)
            while i > 0 and (last is None or wheels[i - 1].host_mono_ns > last):
                i -= 1
            new = wheels[i:]
        for msg in new:
            speed = wheel_speed_mps(msg)
            if speed is None:
                self.state.wheel_messages_without_speed += 1
            else:
                self.odometry.add(msg.host_mono_ns, speed)
        self.state.distance_m = self.odometry.distance_m
        mapped_t = self.odometry.time_at(self.state.mapped_until_m) if self.odometry.knots_t else 0
        self.state.lag_s = max(0.0, (self.odometry.knots_t[-1] - mapped_t) / 1e9) if mapped_t else 0.0

    # ---- windows -----------------------------------------------------------------------------------------
    def _window_ready(self, k: int, end_of_drive: bool) -> bool:
        _, _, s_hi = window_span(k, self.mapper.windows.before_m, self.mapper.windows.after_m)
        if end_of_drive:
            return k < windows_for_drive(self.state.distance_m, self.mapper.windows.before_m,
                                         self.mapper.windows.after_m)
        # the road reaches the window's end, and every input it reads has arrived: its map is then the same
        # whenever the worker gets to it
        return (bool(self.odometry.knots_s) and self.state.distance_m >= s_hi
                and self.reader.complete_until(self.odometry.time_at(s_hi) + INPUT_HORIZON_NS))

    def _window_inputs(self, k: int) -> tuple:
        m = self.mapper
        centre, s_lo, s_hi = window_span(k, m.windows.before_m, m.windows.after_m)
        s_hi = min(s_hi, self.state.distance_m)
        t_lo, t_hi = self.odometry.time_at(s_lo), self.odometry.time_at(s_hi)
        small = self.reader.small_copy()
        horizon = t_hi + INPUT_HORIZON_NS
        traj = self._fuse(small, until_ns=horizon)
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
        anchors = [(a.host_mono_ns, a.utc_ns) for a in small[TIME_ANCHOR] if a.host_mono_ns <= horizon]
        by_topic: dict[str, list] = {}
        for _, topic, msg in records:
            by_topic.setdefault(topic, []).append(msg)
        clocks = {t: span_clock([m.sensor_time_ns for m in v], [m.host_mono_ns for m in v], anchors)
                  for t, v in by_topic.items()}
        # the window's trajectory: poses within [t_lo, t_hi], seconds from t_lo
        inside = (traj.times_ns > t_lo) & (traj.times_ns < t_hi)
        times = np.concatenate([[t_lo], traj.times_ns[inside], [t_hi]]).astype(np.int64)
        pos, _ = traj.interpolate(times)
        path = HorizontalTrack((times - t_lo) / 1e9, pos)
        keyframes = []
        spacing = m.inputs.keyframe_spacing_m
        for cam in self.config.sensors.cameras:
            masks = {x.sensor_time_ns: x for x in by_topic.get(mask_topic(cam.name), [])}
            frames = sorted(by_topic.get(camera_topic(cam.name), []), key=lambda f: f.sensor_time_ns)
            if not frames:
                continue
            host = clocks[camera_topic(cam.name)].to_host([f.sensor_time_ns for f in frames])
            candidates = [(f, t) for f, t in zip(frames, host, strict=True)
                          if t_lo <= t <= t_hi and (self.segmenter is not None or f.sensor_time_ns in masks)]
            for f, t in spaced_by_distance(candidates, lambda ft: float(traj.distance_3d_at(int(ft[1]))[0]), spacing):
                image = decode_image(f)
                keyframes.append(Keyframe(cam.name, (int(t) - t_lo) / 1e9,
                                          camera_pose(traj, int(t), cam.extrinsics.matrix()), image,
                                          keyframe_semantics(image, masks.get(f.sensor_time_ns), self.segmenter)))
        keyframes.sort(key=lambda kf: kf.timestamp)
        ground = None
        packets = by_topic.get(LIDAR_PACKETS, [])
        if packets:
            ground = lidar_ground_from_packets(packets, clocks[LIDAR_PACKETS], self.lidar_meta, self.config, traj, 1,
                                               GroundFilter(corridor_half_width_m=m.mesh.corridor_half_width_m))
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
        seed = m.model.seed * 1_000_003 + k
        np.random.seed(seed % 2**32)
        torch.manual_seed(seed)
        cfg = m.model_copy(update={"model": m.model.model_copy(update={"seed": seed})})
        result = reconstruct(keyframes, self.cameras, path, ground, cfg, self.config.vehicle.reference_height_m,
                             holdout_every=0, progress=False)
        bev = bev_rasters(result.road_map, self.cam_names, self.res, m.runtime.raster_threads)
        j0, i0 = (int(round(v / self.res)) for v in bev["origin_xy"])
        half = (m.windows.before_m + m.windows.after_m) / 4.0
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
        if self.live_view is not None:
            try:
                live_view.publish_window(self.live_view, t_hi, self._preview_images(bev), bev["elevation"],
                                         bev["origin_xy"], self.res, path.positions)
            except Exception as exc:  # the live view never costs a window: counted and reported
                self._error(f"live view, window {k}: {type(exc).__name__}: {exc}")
        wall = time.perf_counter() - started
        keep = ("psnr_train_db", "elev_error_cm", "miou_pct", "steps", "vertices", "vertices_observed",
                "optimise_wall_s", "loss_last")
        extent = ([float(x) for x in path.positions[:, :2].min(0)] + [float(x) for x in path.positions[:, :2].max(0)])
        return {"index": k, "status": "done", "centre_m": centre, "start_m": s_lo, "end_m": s_hi, "seed": seed,
                "wall_s": wall, "finished_mono_ns": time.monotonic_ns(), "tiles": tiles, "trajectory_xy_box": extent,
                "metrics": {x: result.metrics.get(x) for x in keep}, **provenance,
                "config": {"path": self.config_path, "sha256": self.config_sha256}}

    def _preview_images(self, bev: dict) -> dict[str, np.ndarray]:
        return {"rgb": bev["rgb"][self.cam_names[0]], "semantics": semantic_image(bev["labels"]),
                "elevation": elevation_image(bev["elevation"])}

    def _write_previews(self, bev: dict) -> None:
        for name, image in self._preview_images(bev).items():
            _atomic_png(self.previews / f"{name}.png", image)

    def _error(self, what: str) -> None:
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
                    centre, s_lo, s_hi = window_span(k, self.mapper.windows.before_m, self.mapper.windows.after_m)
                    entry = {"index": k, "status": "failed", "centre_m": centre, "start_m": s_lo, "end_m": s_hi,
                             "error": self.health.last_error, "finished_mono_ns": time.monotonic_ns()}
                    self.state.windows_failed += 1
                    break
        entry["attempts"] = attempts
        self.journal["windows"].append(entry)
        self.journal["next_window"] = k + 1
        if entry["status"] == "done":
            self.state.windows_done += 1
            self.state.last_window_wall_s = entry["wall_s"]
        self.state.mapped_until_m = max(self.state.mapped_until_m, min(entry["end_m"], self.state.distance_m))
        self._save_journal(entry)
        _, next_lo, _ = window_span(k + 1, self.mapper.windows.before_m, self.mapper.windows.after_m)
        self.reader.prune(self.odometry.time_at(next_lo) - int(FUSION_MARGIN_S * 1e9))
        return True

    # ---- health ------------------------------------------------------------------------------------------
    def health_message(self):
        st = self.state
        m = self.mapper
        ready = 0
        k = self.journal["next_window"]
        while window_span(k + ready, m.windows.before_m, m.windows.after_m)[2] <= st.distance_m:
            ready += 1
        st.windows_pending = ready
        msg = self.health.snapshot()
        msg.state = "degraded" if self.health.errors else "ok"
        msg.dropped = self.reader.lost
        msg.detail = json.dumps({
            "windows_done": st.windows_done, "windows_failed": st.windows_failed, "windows_pending": ready,
            "distance_m": round(st.distance_m, 2), "mapped_until_m": round(st.mapped_until_m, 2),
            "lag_m": round(max(0.0, st.distance_m - st.mapped_until_m), 2), "lag_s": round(st.lag_s, 2),
            "last_window_wall_s": round(st.last_window_wall_s, 2), "spool_bytes": self.spool.bytes,
            "errors": self.health.errors, "last_error": self.health.last_error, "bus_lost": self.reader.lost,
            "wheel_messages_without_speed": st.wheel_messages_without_speed,
            "live_view": None if self.live_view is None else {"port": self.live_view.port,
                                                              "windows_published": self.live_view.published},
            "finished": st.finished,
            "peak_rss_mb": round(process_memory_mb()["VmHWM"], 1),
        })
        return msg

    # ---- final map ---------------------------------------------------------------------------------------
    def write_final_map(self) -> Path:
        out = self.folder / "final"
        out.mkdir(parents=True, exist_ok=True)
        meta = {"windows": self.journal["windows"], "config": {"path": self.config_path,
                                                                "sha256": self.config_sha256},
                "distance_m": self.state.distance_m, "origin_lat_lon_alt": self.journal["origin"]}
        if map_tiles.tile_indices(self.tiles_dir):
            grid = map_tiles.write_mosaic_npy(self.tiles_dir, self.tile_cells, self.res,
                                              {"elevation": out / "bev_elevation.npy",
                                               "labels": out / "bev_semantics.npy"})
            mos = map_tiles.mosaic(self.tiles_dir, self.tile_cells, self.res, self.cam_names,
                                   max_cells=OVERVIEW_MAX_CELLS)
            for c in self.cam_names:
                _atomic_png(out / f"bev_rgb_{c}.png", mos.rgb[c])
            _atomic_png(out / "bev_semantics.png", semantic_image(mos.labels))
            _atomic_png(out / "bev_elevation.png", elevation_image(mos.elevation))
            meta.update(origin_xy=grid.origin_xy, resolution_m=grid.resolution_m, shape=list(grid.shape),
                        png_resolution_m=mos.resolution_m,
                        cell="cell (i, j) of the .npy rasters is centred at (x0 + j*res, y0 + i*res); "
                             "PNGs (at png_resolution_m) are flipped north-up", semantics_no_label=NO_LABEL,
                        cameras=self.cam_names)
            meta["mesh"] = self._write_mesh(out)
        _atomic_write_text(out / "metadata.json", json.dumps(meta, indent=1, default=str))
        return out

    def _write_mesh(self, out: Path, max_vertices: int = 2_000_000) -> dict:
        """A grid mesh of the mapped cells (cells as vertices, two triangles per fully mapped 2x2 block),
        built from the tiles' mapped cells only."""
        cells = map_tiles.mapped_cells(self.tiles_dir, self.tile_cells, self.res, self.cam_names[0], max_vertices)
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
        for name in ("mesh.ply", "mesh.glb"):
            mesh.export(out / name)
        return {"files": ["mesh.ply", "mesh.glb"], "vertices": len(vertices), "faces": len(faces),
                "resolution_m": res}

    # ---- main loop ---------------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> int:
        torch.set_num_threads(self.mapper.runtime.torch_threads_fast_fit)
        pub = pubsub.open_publisher(self.config, health_topic(PROCESS))
        health_stop = threading.Event()

        def publish_health() -> None:
            while not health_stop.wait(1.0):
                pub.publish(self.health_message())

        health_thread = threading.Thread(target=publish_health, name="mapper-health", daemon=True)
        self.reader.attach()  # registered as a lossless reader before the first health says "up"
        health_thread.start()
        self.reader.start()
        next_odometry = 0.0
        while not stop.is_set():
            if time.monotonic() >= next_odometry:
                self.update_distance()
                next_odometry = time.monotonic() + ODOMETRY_PERIOD_S
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
        if self.live_view is not None:
            live_view.stop_live_view(self.live_view)
        health_stop.set()
        health_thread.join()
        pub.publish(self.health_message())
        pub.close()
        return 0


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapping_worker", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", required=True, help="car config YAML")
    parser.add_argument("--output-dir", help="data folder (default: recorder.output_dir of the config)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s mapper %(levelname)s %(message)s")
    config = load_config(args.config)
    worker = MappingWorker(config, args.config, args.output_dir)  # a ConfigError here: exit 2, not retried
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    return worker.run(stop)


if __name__ == "__main__":
    sys.exit(main())
