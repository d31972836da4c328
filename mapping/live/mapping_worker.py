"""The live mapping worker: `python -m mapping.live.mapping_worker --config PATH [--output-dir DIR]`.

A bus thread subscribes (lossless) to the cameras, masks, Lidar, GNSS, IMU, wheel speeds and time
anchors and appends everything to the disk spool (`mapping.live.keyframe_spool`; Lidar every n-th scan);
GNSS/IMU/wheels/anchors are also kept in memory from the oldest unfinished window on. The main thread
integrates the wheel speeds into the distance travelled (`Odometry`), and as soon as `windows.after_m` of
road lie beyond a window centre and every topic has delivered its data that far (plus the 2 s the
window's inputs reach beyond), it optimises that window ([centre - windows.before_m, centre +
windows.after_m]; centres every half window, so the windows overlap by half) with
`reconstruction.reconstruct` on the window's keyframes, fused trajectory (`drive_inputs.fuse_bus_trajectory`)
and Lidar ground points (frames without a mask are keyframes without semantics, warned about once). What a
window sees depends on the log's content only, never on arrival timing, so replaying a log twice gives the
same map (tests/test_replay_determinism.py).
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
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from daemon.bus import pubsub
from daemon.spine.config import CarConfig, data_dir, load_config, reports_config_errors
from daemon.spine.data_layout import preview_dir
from daemon.spine.health import HealthCounters, process_memory_mb
from daemon.spine.local_frame import LocalFrame
from daemon.spine.process_logging import setup_logging
from daemon.spine.topics import (
    GNSS_FIX,
    IMU,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    TIME_ANCHOR,
    WHEEL_SPEEDS,
    camera_topic,
    health_topic,
    mask_topic,
    topic_table,
)
from mapping.fits.reconstruction import reconstruct
from mapping.inputs.drive_inputs import (
    camera_models,
    camera_pose,
    decode_image,
    fuse_bus_trajectory,
    keyframe_semantics,
    missing_masks_warning,
    segmenter_for,
    spaced_camera_frames,
)
from mapping.inputs.lidar_ground import GroundFilter, configured_decoding, lidar_scans, scans_ground
from mapping.live import live_view, map_tiles
from mapping.live.bus_reader import SMALL_TOPICS, BusReader
from mapping.live.final_map import FinalMapMetadata, TileStore, write_final_map
from mapping.live.keyframe_spool import KeyframeSpool
from mapping.live.map_images import preview_images, write_previews
from mapping.live.odometry import Odometry, wheel_speed_mps
from mapping.live.window_inputs import WindowInputs
from mapping.live.window_schedule import window_span, windows_ended, windows_for_drive
from mapping.live.worker_journal import VERSION as JOURNAL_VERSION
from mapping.live.worker_journal import (
    JournalHeader,
    JournalState,
    WindowEntry,
    append_line,
    header_line,
    progress_line,
    read_journal,
)
from mapping.localization.sensor_time import span_clock
from mapping.localization.trajectory import HorizontalTrack, Trajectory
from mapping.method.compute_device import DEVICES, resolve_device, with_device
from mapping.method.scene_data import Keyframe
from mapping.outputs.map_export import bev_rasters

PROCESS = "mapper"
FUSION_MARGIN_S = 20.0  # data kept (and fused) before the oldest unfinished window starts
ODOMETRY_PERIOD_S = 1.0
INPUT_HORIZON_NS = 2_000_000_000  # a window's inputs reach this far past its end (fusion; clocks 1 s)
TILE_M = 40.0
WINDOW_ATTEMPTS = 2
log = logging.getLogger(__name__)


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
        resolve_device(self.mapper.device, f"{config_path}: mapper.device")  # cuda without a GPU: exit 2
        self.folder = data_dir(config, output_dir) / "map"
        self._archive_finished_map()
        self.tiles_dir = self.folder / "tiles"
        self.previews = preview_dir(self.folder.parent)
        for d in (self.folder, self.tiles_dir, self.previews):
            d.mkdir(parents=True, exist_ok=True)
        self.cameras = camera_models(config)
        self.cam_names = sorted(self.cameras)
        self.segmenter = segmenter_for(config, config_path)  # None: the masks on the bus
        self.masks_warned = False  # frames without masks were reported
        self.res = self.mapper.mesh.side_m
        self.tile_cells = max(1, int(round(TILE_M / self.res)))
        self.tile_store = TileStore(self.tiles_dir, self.tile_cells, self.res, self.cam_names)
        self.health = HealthCounters(PROCESS)
        self.state = WorkerState()
        self.lock = threading.Lock()
        self.spool = KeyframeSpool(self.folder / "spool", topic_table(config), chunk_s=2.0)
        self.journal = self._load_journal()
        self.odometry_saved = len(self.journal.odometry_t)  # knots already in the journal
        self.odometry = Odometry(list(self.journal.odometry_t), list(self.journal.odometry_s),
                                 self.journal.odometry_last_speed_mps)
        self.origin = LocalFrame(*self.journal.origin) if self.journal.origin else None
        lidar = config.sensors.lidar
        self.lidar_decoding = configured_decoding(lidar, config_path) if lidar else None
        last_seq, newest = self.spool.last_seq_and_newest()
        self.reader = BusReader(config, self.spool, self.lock, self.health, last_seq, self.lidar_decoding)
        self.reader.newest.update(newest)
        self._refill_small()
        self.state.windows_done = sum(1 for w in self.journal.windows if w.status == "done")
        self.state.windows_failed = sum(1 for w in self.journal.windows if w.status == "failed")
        self.state.mapped_until_m = self.journal.mapped_until_m
        self.live_view = None
        if self.mapper.live_view.enabled:
            try:
                self.live_view = live_view.start_live_view(self.mapper.live_view)
            except Exception as exc:  # mapping goes on without it
                self._error(f"live view: cannot start: {type(exc).__name__}: {exc}")

    # ---- persistence -------------------------------------------------------------------------------------
    def _archive_finished_map(self) -> None:
        journal = read_journal(self.folder)
        if journal is not None and journal.finished:
            shutil.move(str(self.folder), str(self.folder.with_name(f"map-{time.strftime('%Y%m%d-%H%M%S')}")))

    def _load_journal(self) -> JournalState:
        journal = read_journal(self.folder)
        if journal is None:
            header = JournalHeader(JOURNAL_VERSION, self.config_path, self.config_sha256, self.res, self.tile_cells,
                                   self.cam_names)
            append_line(self.folder, header_line(header))
            return JournalState(header)
        if journal.skipped_lines:
            self._error(f"journal: {journal.skipped_lines} unreadable line(s) skipped (torn by a crash?)")
        return journal

    def _save_journal(self, window: WindowEntry | None = None) -> None:
        """One line: `window` (if any) and the progress since the last line."""
        self.journal.odometry_last_speed_mps = self.odometry.last_speed_mps
        self.journal.mapped_until_m = self.state.mapped_until_m
        self.journal.origin = (None if self.origin is None
                               else [self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m])
        append_line(self.folder, progress_line(self.journal, self.odometry.knots_t, self.odometry.knots_s,
                                               self.odometry_saved, window))
        self.odometry_saved = len(self.odometry.knots_t)

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
        if self.origin is None:
            g = min(gnss, key=lambda m: m.sensor_time_ns)
            self.origin = LocalFrame(g.latitude_deg, g.longitude_deg, g.altitude_m)
        return fuse_bus_trajectory(held, self.config, self.origin)

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
        if end_of_drive:  # a drive without odometry (an empty replay: no wheel speed at all) has no window
            return bool(self.odometry.knots_s) and k < windows_for_drive(
                self.state.distance_m, self.mapper.windows.before_m, self.mapper.windows.after_m)
        # the road reaches the window's end, and every input it reads has arrived: its map is then the same
        # whenever the worker gets to it
        return (bool(self.odometry.knots_s) and self.state.distance_m >= s_hi
                and self.reader.complete_until(self.odometry.time_at(s_hi) + INPUT_HORIZON_NS))

    def _window_inputs(self, k: int) -> WindowInputs:
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
        if self.config.sensors.lidar is not None:
            want |= {LIDAR_PACKETS, LIDAR_POINTS}
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
        keyframes, frames_without_mask, frames_seen = [], 0, 0
        for cam in self.config.sensors.cameras:
            masks = {x.sensor_time_ns: x for x in by_topic.get(mask_topic(cam.name), [])}
            frames = sorted(by_topic.get(camera_topic(cam.name), []), key=lambda f: f.sensor_time_ns)
            if not frames:
                continue
            host = clocks[camera_topic(cam.name)].to_host([f.sensor_time_ns for f in frames])
            inside = [(f, int(t)) for f, t in zip(frames, host, strict=True) if t_lo <= t <= t_hi]
            frames_seen += len(inside)
            frames_without_mask += 0 if self.segmenter else sum(f.sensor_time_ns not in masks for f, _ in inside)
            chosen = spaced_camera_frames(inside, None if self.segmenter else masks, traj, m.inputs.keyframe_spacing_m)
            for f, t, mask in chosen:
                image = decode_image(f)
                keyframes.append(Keyframe(cam.name, (t - t_lo) / 1e9, camera_pose(traj, t, cam.extrinsics.matrix()),
                                          image, keyframe_semantics(image, mask, self.segmenter)))
        keyframes.sort(key=lambda kf: kf.timestamp)
        scans = lidar_scans(by_topic.get(LIDAR_PACKETS, []), by_topic.get(LIDAR_POINTS, []),
                            lambda: self.lidar_decoding, 1)  # every n-th scan: kept by the bus thread
        ground = standing = None
        if scans is not None:  # what stands on the road too, when a keyframe has no mask to leave it out
            occlusion = m.maskless.lidar_occlusion and any(kf.semantics is None for kf in keyframes)
            ground, standing = scans_ground(scans, clocks[scans.topic], self.config, traj,
                                            GroundFilter(corridor_half_width_m=m.mesh.corridor_half_width_m),
                                            t_lo if occlusion else None)
        fed = dict(by_topic)
        for t in (GNSS_FIX, IMU, WHEEL_SPEEDS):
            fed[t] = [x for x in small[t] if t_lo <= x.host_mono_ns <= t_hi]
        seq = {t: [min(x.seq for x in v), max(x.seq for x in v)] for t, v in sorted(fed.items()) if v}
        provenance = {"host_time_ns": [t_lo, t_hi], "seq": seq,
                      "segments": sorted(n for n, (a, b) in self.reader.segments.items() if a <= t_hi and b >= t_lo),
                      "keyframes": len(keyframes), "frames": frames_seen, "frames_without_mask": frames_without_mask,
                      **(scans.counts if scans else {"lidar_packets": 0}),
                      "lidar_ground_points": 0 if ground is None else len(ground)}
        return WindowInputs(centre, s_lo, s_hi, t_lo, t_hi, traj, path, keyframes, ground, provenance, standing)

    def run_window(self, k: int) -> WindowEntry:
        started = time.perf_counter()
        m = self.mapper
        inputs = self._window_inputs(k)
        centre, s_lo, s_hi, t_lo, path = inputs.centre_m, inputs.start_m, inputs.end_m, inputs.t_lo_ns, inputs.path
        if not inputs.keyframes:
            raise ValueError(f"window {k}: no keyframes in [{s_lo:.1f}, {s_hi:.1f}] m")
        warning = missing_masks_warning(inputs.provenance["frames"], inputs.provenance["frames_without_mask"])
        if warning is not None and not self.masks_warned:  # once; each window's counts are in its journal entry
            self.masks_warned = True
            log.warning("window %d: %s", k, warning)
        seed = m.model.seed * 1_000_003 + k
        np.random.seed(seed % 2**32)
        torch.manual_seed(seed)
        cfg = m.model_copy(update={"model": m.model.model_copy(update={"seed": seed})})
        result = reconstruct(inputs.keyframes, self.cameras, path, inputs.ground, cfg,
                             self.config.vehicle.reference_height_m, holdout_every=0, progress=False,
                             lidar_standing=inputs.standing)
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
        images = preview_images(bev, self.cam_names[0], result.road_map.semantic_logits is not None)
        write_previews(self.previews, images)
        if self.live_view is not None:
            try:
                live_view.publish_window(self.live_view, inputs.t_hi_ns, images, bev["elevation"],
                                         bev["origin_xy"], self.res, path.positions)
            except Exception as exc:  # the live view never costs a window: counted and reported
                self._error(f"live view, window {k}: {type(exc).__name__}: {exc}")
        wall = time.perf_counter() - started
        keep = ("psnr_train_db", "elev_error_cm", "miou_pct", "semantics", "keyframes_without_semantics",
                "maskless_hidden_pct", "steps", "vertices", "vertices_observed", "optimise_wall_s", "loss_last")
        extent = ([float(x) for x in path.positions[:, :2].min(0)] + [float(x) for x in path.positions[:, :2].max(0)])
        return WindowEntry(k, "done", centre_m=centre, start_m=s_lo, end_m=s_hi, seed=seed, wall_s=wall,
                           finished_mono_ns=time.monotonic_ns(), tiles=tiles, trajectory_xy_box=extent,
                           metrics={x: result.metrics.get(x) for x in keep}, **inputs.provenance,
                           config={"path": self.config_path, "sha256": self.config_sha256})

    def _error(self, what: str) -> None:
        self.health.count_error(what)
        log.error("%s", what)

    def step(self, end_of_drive: bool) -> bool:
        """Optimise the next window if it is ready; False when there is nothing to do now."""
        k = self.journal.next_window
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
                    entry = WindowEntry(k, "failed", centre_m=centre, start_m=s_lo, end_m=s_hi,
                                        error=self.health.last_error, finished_mono_ns=time.monotonic_ns())
                    self.state.windows_failed += 1
                    break
        entry.attempts = attempts
        self.journal.windows.append(entry)
        self.journal.next_window = k + 1
        if entry.status == "done":
            self.state.windows_done += 1
            self.state.last_window_wall_s = entry.wall_s
        self.state.mapped_until_m = max(self.state.mapped_until_m, min(entry.end_m, self.state.distance_m))
        self._save_journal(entry)
        _, next_lo, _ = window_span(k + 1, self.mapper.windows.before_m, self.mapper.windows.after_m)
        self.reader.prune(self.odometry.time_at(next_lo) - int(FUSION_MARGIN_S * 1e9))
        return True

    # ---- health ------------------------------------------------------------------------------------------
    def health_message(self):
        st = self.state
        m = self.mapper
        ready = windows_ended(self.journal.next_window, st.distance_m, m.windows.before_m, m.windows.after_m)
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
        out = write_final_map(self.folder / "final", self.tile_store, FinalMapMetadata(
            windows=[w.to_json() for w in self.journal.windows],
            config={"path": self.config_path, "sha256": self.config_sha256}, distance_m=self.state.distance_m,
            origin_lat_lon_alt=self.journal.origin))
        self.state.finished = True
        self.journal.finished = True
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
    parser.add_argument("--device", choices=DEVICES, help="torch device of the fits (default: mapper.device)")
    args = parser.parse_args(argv)
    setup_logging("mapper")
    config = with_device(load_config(args.config), args.device)
    worker = MappingWorker(config, args.config, args.output_dir)  # a ConfigError here: exit 2, not retried
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    return worker.run(stop)


if __name__ == "__main__":
    sys.exit(main())
