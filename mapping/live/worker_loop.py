"""The live mapping worker's loop (its process: `mapping.live.mapping_worker`).

A bus thread subscribes (lossless) to the cameras, masks, Lidar, GNSS, IMU, wheel speeds and time
anchors and appends everything to the disk spools (`mapping.live.keyframe_spool`; Lidar every n-th scan;
GNSS/IMU/wheels/anchors in a spool of their own, read back for each window's fusion over its span and a 20 s
margin: nothing in memory grows with how far behind the worker is, `mapping.live.bus_reader`). The main thread
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
recorder/replay health, the config's path and hash). A worker more than `mapper.lag.max_behind_m` behind the
car skips ahead (`mapping.live.lag_policy`: the windows skipped journalled and counted). On SIGTERM/SIGINT the
worker drains the bus, finishes the remaining windows (the last one shorter) that end within its stop timeout
less `mapper.lag.stop_reserve_s` (the others journalled skipped), writes the final map under `<data>/map/final`
and exits 0. Killed, it resumes from the journal, tiles and spool on its next start. A failed window is
counted, reported and retried; after its last attempt it is recorded as failed in the journal and the
worker moves on. With
`mapper.live_view.enabled` each finished window is also published on a Foxglove WebSocket server
(`mapping.live.live_view`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from daemon.bus import pubsub
from daemon.spine.config import CarConfig, data_dir
from daemon.spine.data_layout import preview_dir
from daemon.spine.health import HealthCounters, process_memory_mb
from daemon.spine.local_frame import LocalFrame
from daemon.spine.topics import (
    GNSS_FIX,
    IMU,
    TIME_ANCHOR,
    WHEEL_SPEEDS,
    health_topic,
    topic_table,
)
from mapping.fits.reconstruction import reconstruct
from mapping.inputs.drive_inputs import (
    camera_models,
    fuse_bus_trajectory,
    missing_masks_warning,
    segmenter_for,
)
from mapping.inputs.lidar_ground import configured_decoding
from mapping.live import lag_policy, live_view, map_tiles
from mapping.live.bus_reader import BusReader
from mapping.live.final_map import FinalMapMetadata, TileStore, write_final_map
from mapping.live.heap_trim import return_freed_memory
from mapping.live.keyframe_spool import KeyframeSpool
from mapping.live.map_images import preview_images, write_previews
from mapping.live.odometry import Odometry, wheel_speed_mps
from mapping.live.window_inputs import FUSION_MARGIN_S, INPUT_HORIZON_NS, gather_window_inputs
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
from mapping.localization.trajectory import Trajectory
from mapping.method.compute_device import resolve_device
from mapping.outputs.map_export import bev_rasters

PROCESS = "mapper"
ODOMETRY_PERIOD_S = 1.0
TILE_M = 40.0
WINDOW_ATTEMPTS = 2
log = logging.getLogger(__name__)


@dataclass
class WorkerState:
    """What /status and the journal show of the worker's progress."""

    windows_done: int = 0
    windows_failed: int = 0
    windows_skipped: int = 0  # behind the car (mapper.lag.max_behind_m) or left at the stop
    skipped_m: float = 0.0  # the road those windows' central stretches cover
    windows_pending: int = 0
    distance_m: float = 0.0
    mapped_until_m: float = 0.0
    lag_s: float = 0.0
    last_window_wall_s: float = 0.0
    wheel_messages_without_speed: int = 0
    windows_without_lidar_refinement: int = 0  # mapper.pose_refinement.lidar_horizontal asked for, no Lidar ground
    # in the window: the photometric refinement took its place (each window's reason in its journal metrics)
    finished: bool = False


class MappingWorker:
    def __init__(self, config: CarConfig, config_path: str, output_dir: str | None = None, skips: bool = True):
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
        self.odometry_lock = threading.Lock()  # the health thread reads the odometry while the main loop adds to it
        self.spool = KeyframeSpool(self.folder / "spool", topic_table(config), chunk_s=2.0)
        self.small_spool = KeyframeSpool(self.spool.folder / "small", topic_table(config), chunk_s=10.0)
        self.max_behind_m = self.mapper.lag.max_behind_m if skips else None
        self.recent_walls: deque[float] = deque(maxlen=3)  # the last windows' wall times (the stop's estimate)
        self.stop_left: dict | None = None  # what the stop left unfitted (health)
        self.journal = self._load_journal()
        self.odometry_saved = len(self.journal.odometry_t)  # knots already in the journal
        self.odometry = Odometry(self.journal.odometry_t, self.journal.odometry_s,
                                 self.journal.odometry_last_speed_mps)
        self.journal.odometry_t, self.journal.odometry_s = [], []  # the odometry's now (saved by _save_journal)
        self.origin = LocalFrame(*self.journal.origin) if self.journal.origin else None
        lidar = config.sensors.lidar
        self.lidar_decoding = configured_decoding(lidar, config_path) if lidar else None
        last_seq, newest = self.spool.last_seq_and_newest()
        small_seq, small_newest = self.small_spool.last_seq_and_newest()
        self.reader = BusReader(config, self.spool, self.small_spool, self.lock, self.health, last_seq | small_seq,
                                self.lidar_decoding)
        self.reader.newest.update(newest | small_newest)
        self._refill_small()
        for w in self.journal.windows:
            self.state.windows_done += w.status == "done"
            self.state.windows_failed += w.status == "failed"
            self.state.windows_skipped += w.status == "skipped"
            self.state.skipped_m += self._central_m(w.index) if w.status == "skipped" else 0.0
            self.state.windows_without_lidar_refinement += bool((w.metrics or {}).get(
                "pose_refinement_lidar_unavailable"))
        self.journal.windows = []  # on disk; the final map reads them back: memory does not grow with the drive
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
        """After a restart: the spooled anchors, and the wheel speeds past the journal's odometry."""
        if not self.small_spool.chunks:
            return
        last = self.odometry.knots_t[-1] if self.odometry.knots_t else None
        for _, topic, msg in self.small_spool.read(self.small_spool.chunks[0].first_ns,
                                                   self.small_spool.chunks[-1].last_ns, {WHEEL_SPEEDS, TIME_ANCHOR}):
            if topic == TIME_ANCHOR:
                self.reader.anchors.append(msg)
            elif last is None or msg.host_mono_ns > last:
                self.reader.wheels.append(msg)

    # ---- trajectory --------------------------------------------------------------------------------------
    def fuse(self, held: dict[str, list]) -> Trajectory | None:
        """The trajectory from the GNSS, IMU and wheel speeds read for a window."""
        gnss, imu, wheels = held[GNSS_FIX], held[IMU], held[WHEEL_SPEEDS]
        if len(gnss) < 5 or len(imu) < 20 or len(wheels) < 10:
            return None
        if self.origin is None:
            g = min(gnss, key=lambda m: m.sensor_time_ns)
            self.origin = LocalFrame(g.latitude_deg, g.longitude_deg, g.altitude_m)
        return fuse_bus_trajectory(held, self.config, self.origin)

    def update_distance(self) -> None:
        """Integrate the wheel speeds that arrived since the last call into the odometry."""
        with self.odometry_lock:
            for msg in self.reader.take_wheels():
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

    def run_window(self, k: int) -> WindowEntry:
        started = time.perf_counter()
        m = self.mapper
        inputs = gather_window_inputs(self, k)
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
                             lidar_standing=inputs.standing, lidar_ground_times=inputs.ground_times,
                             lidar_ground_contrast=inputs.ground_contrast)
        unavailable = result.metrics.get("pose_refinement", {}).get("lidar_unavailable")
        if unavailable is not None:
            self.state.windows_without_lidar_refinement += 1
            if self.state.windows_without_lidar_refinement == 1:  # once; counted on /status
                log.warning("window %d: mapper.pose_refinement.lidar_horizontal asked for, but %s: the photometric "
                            "refinement instead", k, unavailable)
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
        floor = m.lag.min_window_wall_s  # a slow mapper's stand-in (tests, soaks)
        if time.perf_counter() - started < floor:
            time.sleep(floor - (time.perf_counter() - started))
        wall = time.perf_counter() - started
        keep = ("psnr_train_db", "elev_error_cm", "miou_pct", "semantics", "keyframes_without_semantics",
                "maskless_hidden_pct", "steps", "vertices", "vertices_observed", "optimise_wall_s", "loss_last")
        extent = ([float(x) for x in path.positions[:, :2].min(0)] + [float(x) for x in path.positions[:, :2].max(0)])
        return WindowEntry(k, "done", centre_m=centre, start_m=s_lo, end_m=s_hi, seed=seed, wall_s=wall,
                           finished_mono_ns=time.monotonic_ns(), tiles=tiles, trajectory_xy_box=extent,
                           metrics={**{x: result.metrics.get(x) for x in keep},
                                    "pose_refinement_lidar_unavailable": unavailable}, **inputs.provenance,
                           config={"path": self.config_path, "sha256": self.config_sha256})

    def _error(self, what: str) -> None:
        self.health.count_error(what)
        log.error("%s", what)

    def step(self, end_of_drive: bool) -> bool:
        """Optimise the next window if it is ready; False when there is nothing to do now. Live, a worker more
        than `mapper.lag.max_behind_m` behind the car first skips to the newest window that has ended."""
        k = self.journal.next_window
        m = self.mapper.windows
        if not end_of_drive:
            skip = lag_policy.windows_to_skip(k, self.state.distance_m, m.before_m, m.after_m, self.max_behind_m)
            if skip:
                _, _, end_m = window_span(k, m.before_m, m.after_m)
                self._skip(range(k, k + skip), lag_policy.BEHIND,
                           f"window {k} ended {self.state.distance_m - end_m:.0f} m behind the car "
                           f"(mapper.lag.max_behind_m {self.max_behind_m:g})")
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
                    centre, s_lo, s_hi = window_span(k, m.before_m, m.after_m)
                    entry = WindowEntry(k, "failed", centre_m=centre, start_m=s_lo, end_m=s_hi,
                                        error=self.health.last_error, finished_mono_ns=time.monotonic_ns())
                    self.state.windows_failed += 1
                    break
        entry.attempts = attempts
        self.journal.next_window = k + 1
        if entry.status == "done":
            self.state.windows_done += 1
            self.state.last_window_wall_s = entry.wall_s
            self.recent_walls.append(entry.wall_s)
        self.state.mapped_until_m = max(self.state.mapped_until_m, min(entry.end_m, self.state.distance_m))
        return_freed_memory()
        if entry.metrics is not None:  # the worker's memory after each window, in the journal (soaks)
            entry.metrics["rss_mb_after_window"] = round(process_memory_mb()["VmRSS"], 1)
        self._save_journal(entry)
        self._prune_for(k + 1)
        self.update_distance()  # the wheel speeds that came during the window
        return True

    def _prune_for(self, k: int) -> None:
        """Delete what no window from `k` on needs (its fusion reaches FUSION_MARGIN_S before its start)."""
        _, next_lo, _ = window_span(k, self.mapper.windows.before_m, self.mapper.windows.after_m)
        self.reader.prune(self.odometry.time_at(next_lo) - int(FUSION_MARGIN_S * 1e9))

    def _central_m(self, k: int) -> float:
        """The length of road window k's central stretch covers (the stretch its map is kept from)."""
        m = self.mapper.windows
        centre, _, _ = window_span(k, m.before_m, m.after_m)
        half = (m.before_m + m.after_m) / 4.0
        return max(0.0, min(centre + half, self.state.distance_m) - max(0.0, centre - half))

    def _skip(self, windows: range, reason: str, why: str) -> None:
        """Journal `windows` as skipped (their span, host times and log segments, for `roadlog reconstruct`),
        count them, and say so once in the log."""
        m = self.mapper.windows
        skipped_m = 0.0
        for k in windows:
            centre, s_lo, s_hi = window_span(k, m.before_m, m.after_m)
            t_lo = self.odometry.time_at(s_lo) if self.odometry.knots_t else None
            t_hi = self.odometry.time_at(min(s_hi, self.state.distance_m)) if self.odometry.knots_t else None
            segments = None if t_lo is None else sorted(
                n for n, (a, b) in self.reader.segments.items() if a <= t_hi and b >= t_lo)
            entry = WindowEntry(k, "skipped", centre_m=centre, start_m=s_lo, end_m=s_hi, reason=f"{reason}: {why}",
                                finished_mono_ns=time.monotonic_ns(),
                                host_time_ns=None if t_lo is None else [t_lo, t_hi], segments=segments)
            self.journal.next_window = k + 1
            self.state.windows_skipped += 1
            skipped_m += self._central_m(k)
            self._save_journal(entry)
        self.state.skipped_m += skipped_m
        log.warning("skipped windows %d-%d (%.0f m of road): %s; they are journalled as skipped with their log "
                    "segments (roadlog reconstruct maps them)", windows.start, windows.stop - 1, skipped_m, why)
        self._prune_for(windows.stop)

    # ---- health ------------------------------------------------------------------------------------------
    def distance_now_m(self) -> float:
        """The distance driven with the wheel speeds the odometry has not taken yet (it takes them between windows:
        while one is fitted, `state.distance_m` stands still and the car does not)."""
        with self.odometry_lock:
            pending = [(msg.host_mono_ns, v) for msg in self.reader.pending_wheels()
                       if (v := wheel_speed_mps(msg)) is not None]
            return self.odometry.distance_after(pending)

    def health_message(self):
        st = self.state
        m = self.mapper
        distance_m = self.distance_now_m()
        ready = windows_ended(self.journal.next_window, distance_m, m.windows.before_m, m.windows.after_m)
        st.windows_pending = ready
        msg = self.health.snapshot()
        msg.state = "degraded" if self.health.errors or st.windows_skipped else "ok"
        msg.dropped = self.reader.lost
        msg.detail = json.dumps({
            "windows_done": st.windows_done, "windows_failed": st.windows_failed, "windows_pending": ready,
            "windows_skipped": st.windows_skipped, "skipped_m": round(st.skipped_m, 1),
            "max_behind_m": self.max_behind_m,
            "distance_m": round(distance_m, 2), "mapped_until_m": round(st.mapped_until_m, 2),
            "lag_m": round(max(0.0, distance_m - st.mapped_until_m), 2), "lag_s": round(st.lag_s, 2),
            "last_window_wall_s": round(st.last_window_wall_s, 2),
            "spool_bytes": self.spool.bytes + self.small_spool.bytes,
            "errors": self.health.errors, "last_error": self.health.last_error, "bus_lost": self.reader.lost,
            "wheel_messages_without_speed": st.wheel_messages_without_speed,
            "windows_without_lidar_refinement": st.windows_without_lidar_refinement,
            "live_view": None if self.live_view is None else {"port": self.live_view.port,
                                                              "windows_published": self.live_view.published},
            "held": self.reader.held() | {"odometry_knots": len(self.odometry.knots_t)},
            "stop": self.stop_left,
            "finished": st.finished,
            "rss_mb": round(process_memory_mb()["VmRSS"], 1),
            "peak_rss_mb": round(process_memory_mb()["VmHWM"], 1),
        })
        return msg

    # ---- main loop ---------------------------------------------------------------------------------------
    def run(self, stop: lag_policy.StopRequest, stop_timeout_s: float | None = None) -> int:
        torch.set_num_threads(self.mapper.runtime.torch_threads_fast_fit)
        pub = pubsub.open_publisher(self.config, health_topic(PROCESS))
        health_stop = threading.Event()

        def publish_health() -> None:
            while not health_stop.wait(1.0):
                pub.publish(self.health_message())

        health_thread = threading.Thread(target=publish_health, name="mapper-health", daemon=True)
        self.reader.attach()  # registered as a lossless reader before the first health says "up"
        pub.publish(self.health_message())
        health_thread.start()
        self.reader.start()
        next_odometry = 0.0
        while not stop.event.is_set():
            if time.monotonic() >= next_odometry:
                self.update_distance()
                next_odometry = time.monotonic() + ODOMETRY_PERIOD_S
            if not self.step(end_of_drive=False):
                stop.event.wait(0.2)
        deadline = lag_policy.stop_deadline(stop.at or time.monotonic(), stop_timeout_s, self.mapper.lag.stop_reserve_s)
        log.info("stopping: draining the bus and finishing the remaining windows%s",
                 "" if deadline is None else f" that end within {deadline - time.monotonic():.0f} s")
        self.reader.stop_requested.set()
        if not self.reader.drained.wait(None if deadline is None else max(1.0, deadline - time.monotonic())):
            self._error("stop: the bus was not drained by the stop deadline; the map ends where the spool does")
        self.update_distance()
        self._finish_windows(deadline)
        windows = [w.to_json() for w in read_journal(self.folder).windows]
        out = write_final_map(self.folder / "final", self.tile_store, FinalMapMetadata(
            windows=windows, config={"path": self.config_path, "sha256": self.config_sha256},
            distance_m=self.state.distance_m, origin_lat_lon_alt=self.journal.origin))
        self.state.finished = True
        self.journal.finished = True
        self._save_journal()
        shutil.rmtree(self.spool.folder)  # every window is in the tiles and the final map, or journalled skipped
        self.spool.chunks = []
        self.small_spool.chunks = []
        log.info("final map in %s (%d windows done, %d failed, %d skipped)%s", out, self.state.windows_done,
                 self.state.windows_failed, self.state.windows_skipped,
                 "" if stop.at is None else f", {time.monotonic() - stop.at:.1f} s after the stop request")
        if self.live_view is not None:
            live_view.stop_live_view(self.live_view)
        health_stop.set()
        health_thread.join()
        pub.publish(self.health_message())
        pub.close()
        return 0

    def _finish_windows(self, deadline: float | None) -> None:
        """The remaining windows of the drive, as far as they end by `deadline`; the rest journalled skipped."""
        m = self.mapper
        total = (windows_for_drive(self.state.distance_m, m.windows.before_m, m.windows.after_m)
                 if self.odometry.knots_s else 0)
        while self.journal.next_window < total:
            expected = lag_policy.expected_window_s(list(self.recent_walls), m.lag.min_window_wall_s)
            if not lag_policy.window_fits(time.monotonic(), deadline, expected):
                left = range(self.journal.next_window, total)
                self.stop_left = {"windows": len(left), "first": left.start, "expected_window_s": round(expected, 1),
                                  "seconds_left": round(deadline - time.monotonic(), 1)}
                self._skip(left, lag_policy.STOP, f"{len(left)} window(s) of ~{expected:.0f} s each would not end "
                           f"within the stop timeout less mapper.lag.stop_reserve_s {m.lag.stop_reserve_s:g} s")
                return
            if not self.step(end_of_drive=True):
                return
