"""`roadlog simulate`: drive a scenario and write the drive log the recorder would have written (MCAP, all
sensor topics in host arrival order) and, beside it, PATH.gt.npz with the ground truth. With --no-masks the
log has no mask topics (a car without a segmenter); its images are the same as with them.

Camera frames and Lidar scans are rendered in worker processes; GNSS/IMU bytes go through the GNSS
driver's own framer and decoder and CAN frames through the CAN driver's decoder, the Lidar's own IMU
through its LEGACY packets and the Lidar driver's decoder, so the logged fixes, velocities, IMU samples and wheel
speeds are exactly what those drivers would have published.

Ground truth (PATH.gt.npz), all in the scenario's local ENU frame:
  enu_origin_lat_lon_alt (3,); grid_origin_xy (2,) lower-left corner of cell (0, 0); grid_resolution_m;
  elevation (rows, cols) float32 (NaN outside the corridor); semantic (rows, cols) uint8 (255 outside);
  albedo (rows, cols, 3) uint8 linear RGB * 255; row i spans y = origin_y + [i, i+1) * res, column j x.
  trajectory_host_mono_ns, trajectory_position_enu (N, 3) of the vehicle reference point,
  trajectory_quaternion_xyzw (N, 4) vehicle -> ENU, at 200 Hz on the log's host monotonic clock;
  lidar_points_enu (M, 3) float32 true road-surface points hit by the Lidar inside the grids' corridor
  (noise-free, every LIDAR_GT_EVERY-th scan) and lidar_points_class (M,); host_mono_at_start_ns,
  utc_start_ns (the log's host monotonic and UTC clocks at the drive's start); scenario_yaml, the whole
  scenario, for a world that is not one of configs/scenarios/ (a random world: `--scenario random --seed N`).
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import json
import multiprocessing
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from daemon.log_format.writer import LogWriter
from daemon.spine.config import CarConfig, ConfigError, load_config, reports_config_errors, resolve_path
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import CameraFrame, CanFrame, ImuSample, LidarPacket, SemanticMask, TimeAnchor
from daemon.spine.topics import (
    CAN_FRAMES,
    GNSS_TOPIC_BY_TYPE,
    LIDAR_IMU,
    LIDAR_PACKETS,
    TIME_ANCHOR,
    WHEEL_SPEEDS,
    camera_topic,
    mask_topic,
)
from drivers.can.wheel_speed_codec import WheelSpeedDecoder, load_dbc, wheel_speed_layout
from drivers.gnss.gnss_messages import GnssDecoder
from drivers.gnss.stream_framer import StreamFramer
from drivers.lidar.ouster_imu import decode_imu_packet, encode_imu_packet
from drivers.lidar.ouster_metadata import parse_metadata
from sim.sensors import can_sim, gnss_sim, imu_sim
from sim.sensors.camera_renderer import camera_rig, render_view
from sim.sensors.camera_response import encode_jpeg, expose, vignetting_map
from sim.sensors.lidar_sim import ouster_rig, simulate_scan
from sim.sensors.semantic_mask_sim import encode_mask_png, segmentation_mask
from sim.sensors.sensor_clocks import (
    ESF_TICK_NS,
    HOST_MONO_AT_START_NS,
    SensorClock,
    drive_clocks,
    host_arrival_ns,
    host_mono_ns,
    sensor_stamp_ns,
    utc_start_ns,
)
from sim.sensors.velodyne_sim import velodyne_rig
from sim.world.random_world import scenario_for
from sim.world.revisit import visit
from sim.world.road_world import ground_truth_grids, is_road_surface
from sim.world.scenarios import Scenario, scenario_names
from sim.world.scene import Scene, build_scene

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "sim.yaml"
LIDAR_GT_EVERY = 5
LIDAR_IMU_RATE_HZ = 100.0  # an Ouster's IMU packets
TRAJECTORY_HZ = 200.0

# Worker state, inherited through fork (set before the pool starts).
_SCENE: Scene | None = None
_CLOCKS: dict[str, SensorClock] = {}
_LIDAR_METADATA: Path | None = None
_RIGS: dict[str, object] = {}
_MASKS = True  # the camera tasks make segmentation masks


@dataclass
class SimulationSummary:
    scenario: str
    seconds: float
    seed: int
    out: Path
    ground_truth: Path
    messages: dict[str, int] = field(default_factory=dict)
    camera_frames: int = 0
    lidar_scans: int = 0
    wall_s: float = 0.0
    setup_s: float = 0.0  # scene, GNSS/IMU/CAN streams (before rendering starts)
    render_s: float = 0.0  # cameras and Lidar rendered, everything written to the log
    ground_truth_s: float = 0.0
    bytes_written: int = 0
    world: dict | None = None  # the whole scenario, for a world not in configs/scenarios/ (a random one)

    def as_json(self) -> str:
        d = dict(self.__dict__, out=str(self.out), ground_truth=str(self.ground_truth))
        if d["world"] is None:
            del d["world"]
        return json.dumps(d)


def scenario_yaml(scenario: Scenario) -> str:
    """The scenario as a file `--scenario PATH.yaml` reads back to the same world."""
    return yaml.safe_dump(scenario.model_dump(mode="json"), sort_keys=False)


# --- worker tasks -------------------------------------------------------------------------------

def _camera_task(task: tuple) -> tuple:
    _, cam_index, frame_index, true_s = task
    scene = _SCENE
    cam = scene.config.sensors.cameras[cam_index]
    key = f"camera/{cam.name}"
    if key not in _RIGS:
        _RIGS[key] = (camera_rig(cam), vignetting_map(cam.width, cam.height, cam.intrinsics.cx, cam.intrinsics.cy,
                                                      cam.photometry.vignetting))
    rig, vignette = _RIGS[key]
    rng = np.random.default_rng([scene.seed, 10, cam_index, frame_index])
    view = render_view(scene, rig, true_s)
    light = scene.scenario.lighting
    rgb = expose(view.radiance, cam.photometry, vignette, light.exposure, light.noise_scale,
                 int(rng.integers(1 << 31)))
    png = encode_mask_png(segmentation_mask(view.labels, view.depth, rng)) if _MASKS else None
    return ("camera", cam_index, frame_index, true_s, encode_jpeg(rgb, cam.jpeg_quality), png)


def _lidar_task(task: tuple) -> tuple:
    _, frame_id, start_s = task
    scene = _SCENE
    if "lidar" not in _RIGS:
        lidar = scene.config.sensors.lidar
        _RIGS["lidar"] = (velodyne_rig if lidar.vendor_packets else ouster_rig)(lidar, _LIDAR_METADATA)
    rig = _RIGS["lidar"]
    rng = np.random.default_rng([scene.seed, 20, frame_id])
    scan = simulate_scan(scene, rig, frame_id, start_s, rng)
    clock = _CLOCKS["lidar"]
    stamps = sensor_stamp_ns(clock, scan.column_time_s, rng)
    packets, packet_stamps = rig.encode(scan, stamps)
    k = rig.columns_per_packet
    last_column = scan.column_time_s[k - 1::k]
    arrivals = np.maximum.accumulate(host_arrival_ns(clock, last_column, rng))
    points = classes = None
    if frame_id % LIDAR_GT_EVERY == 0:
        road = is_road_surface(scan.hit_class)
        points, classes = scan.hit_world[road], scan.hit_class[road]
    return ("lidar", frame_id, start_s, packets, packet_stamps, arrivals, points, classes)


def _run_task(task: tuple) -> tuple:
    return _camera_task(task) if task[0] == "camera" else _lidar_task(task)


def _init_worker() -> None:
    cv2.setNumThreads(1)


# --- streams generated in the main process ------------------------------------------------------

def _event_times(rate_hz: float, phase_s: float, seconds: float) -> np.ndarray:
    return np.arange(phase_s, seconds, 1.0 / rate_hz)


def _gnss_imu_messages(scene: Scene, clocks: dict[str, SensorClock], frame: LocalFrame, rng: np.random.Generator
                       ) -> list[tuple[int, str, object]]:
    """Fixes, velocities and IMU samples as the GNSS driver decodes them from the receiver's byte stream."""
    gnss = scene.config.sensors.gnss
    utc0 = utc_start_ns(scene.scenario)
    fix_s = _event_times(gnss.rate_hz, 1.0 / gnss.rate_hz - (utc0 % 100_000_000) / 1e9, scene.seconds)
    fix_utc = sensor_stamp_ns(clocks["gnss"], fix_s, rng)
    epochs = gnss_sim.antenna_epochs(scene.ego, frame, np.array(gnss.antenna_lever_arm_m), fix_s, fix_utc,
                                     scene.scenario.gnss.quality, rng)
    chunks = [(int(h), gnss_sim.epoch_bytes(e)) for h, e in zip(host_arrival_ns(clocks["gnss"], fix_s, rng),
                                                                   epochs, strict=True)]
    imu_s = _event_times(gnss.imu_rate_hz, rng.uniform(0, 1.0 / gnss.imu_rate_hz), scene.seconds)
    force, rate = imu_sim.imu_readings(scene.ego, gnss.imu_extrinsics.matrix(), imu_s, rng)
    ticks = np.floor(sensor_stamp_ns(clocks["imu"], imu_s, rng) / ESF_TICK_NS).astype(np.int64)
    arrivals = host_arrival_ns(clocks["imu"], imu_s, rng)
    chunks += [(int(arrivals[i]), imu_sim.esf_raw_bytes(force[i], rate[i], int(ticks[i]))) for i in range(len(imu_s))]
    chunks.sort(key=lambda c: c[0])
    framer, decoder = StreamFramer(), GnssDecoder(gnss.protocol)
    out = []
    for host_ns, data in chunks:
        for fr in framer.feed(data):
            for msg in decoder.decode(fr, host_ns):
                out.append((host_ns, GNSS_TOPIC_BY_TYPE[type(msg)], msg))
    return out


def _lidar_imu_messages(scene: Scene, clocks: dict[str, SensorClock], rng: np.random.Generator
                        ) -> list[tuple[int, str, object]]:
    """The Lidar's own IMU at 100 Hz on the Lidar's clock, as the Lidar driver decodes its LEGACY packets."""
    lidar = scene.config.sensors.lidar
    metadata = parse_metadata(_LIDAR_METADATA)
    imu_to_vehicle = lidar.extrinsics.matrix() @ metadata.imu_to_sensor_transform
    times = _event_times(LIDAR_IMU_RATE_HZ, rng.uniform(0, 1.0 / LIDAR_IMU_RATE_HZ), scene.seconds)
    force, rate = imu_sim.imu_readings(scene.ego, imu_to_vehicle, times, rng)
    stamps = sensor_stamp_ns(clocks["lidar"], times, rng)
    arrivals = host_arrival_ns(clocks["lidar"], times, rng)
    out = []
    for i in range(len(times)):
        packet = encode_imu_packet(ImuSample(sensor_time_ns=int(stamps[i]), accel_mps2=tuple(force[i]),
                                             gyro_rps=tuple(rate[i])))
        out.append((int(arrivals[i]), LIDAR_IMU, decode_imu_packet(packet, int(arrivals[i]))))
    return out


def _can_messages(scene: Scene, clocks: dict[str, SensorClock], dbc_path: Path, rng: np.random.Generator
                  ) -> list[tuple[int, str, object]]:
    can_cfg = scene.config.sensors.can
    db = load_dbc(dbc_path)
    times = _event_times(can_sim.RATE_HZ, rng.uniform(0, 1 / can_sim.RATE_HZ), scene.seconds)
    speeds, yaw = can_sim.wheel_speeds(scene.ego, scene.config.vehicle, times, rng)
    decoder = WheelSpeedDecoder(wheel_speed_layout(db, can_cfg.signals))
    out = []
    for i, frames in enumerate(can_sim.can_messages(db, can_cfg.signals, speeds, yaw)):
        for j, msg in enumerate(frames):
            t = times[i] + j * 0.0002
            host = int(host_arrival_ns(clocks["can"], np.array([t]), rng)[0])
            stamp = int(sensor_stamp_ns(clocks["can"], np.array([(host - HOST_MONO_AT_START_NS) / 1e9]), rng)[0])
            frame = CanFrame(sensor_time_ns=stamp, host_mono_ns=host, arbitration_id=msg.arbitration_id,
                             is_extended_id=msg.is_extended_id, channel=can_cfg.channel, data=bytes(msg.data))
            out.append((host, CAN_FRAMES, frame))
            speeds_msg = decoder.decode(frame.arbitration_id, frame.is_extended_id, frame.data, stamp)
            if speeds_msg is not None:
                speeds_msg.host_mono_ns = host
                out.append((host, WHEEL_SPEEDS, speeds_msg))
    return out


# --- the drive ----------------------------------------------------------------------------------

def _tasks(scene: Scene, rng: np.random.Generator) -> list[tuple]:
    tasks = []
    for ci, cam in enumerate(scene.config.sensors.cameras):
        for fi, t in enumerate(_event_times(cam.rate_hz, rng.uniform(0.01, 1.0 / cam.rate_hz), scene.seconds)):
            tasks.append(("camera", ci, fi, float(t)))
    lidar = scene.config.sensors.lidar
    if lidar is not None:
        for fi, t in enumerate(_event_times(lidar.rate_hz, rng.uniform(0, 0.02), scene.seconds - 1.0 / lidar.rate_hz)):
            tasks.append(("lidar", fi, float(t)))
    tasks.sort(key=lambda task: task[-1] if task[0] == "camera" else task[2])
    return tasks


def _gt_path(out: Path) -> Path:
    return out.with_name(out.name.removesuffix(".mcap") + ".gt.npz")


def simulate_drive(scenario: str, seconds: float | None, out: Path, config: CarConfig, seed: int | None = None,
                   config_dir: Path | None = None, workers: int = 2, masks: bool = True,
                   visit_number: int = 0) -> SimulationSummary:
    """Simulate a drive and write `out` (MCAP) and its ground truth beside it; relative sensor files of the
    config (Lidar metadata, DBC) are taken from config_dir (default: the repository's configs/). `masks`
    False leaves the mask topics out (the frames are the same). `scenario` `random` draws the world of `seed`
    (sim/world/random_world.py). `visit_number` > 0 drives the same world again on another day (sim/world/revisit.py:
    other traffic, light, noise and GNSS offset); the truth is the same world's."""
    global _SCENE, _CLOCKS, _LIDAR_METADATA, _MASKS
    started = time.monotonic()
    cv2.setNumThreads(1)  # OpenCV's thread pool does not survive fork(): the workers would hang
    sc = scenario_for(scenario, seed, [cam.name for cam in config.sensors.cameras])
    seconds = sc.drive.default_seconds if seconds is None else float(seconds)
    if not 0 < seconds <= sc.max_seconds():
        raise ValueError(f"scenario {sc.name}: seconds must be in (0, {sc.max_seconds():.1f}], got {seconds}")
    world_seed = sc.seed if seed is None else seed
    trip = visit(sc, world_seed, visit_number)
    sc, seed = trip.scenario, trip.drive_seed
    config_file = (config_dir or DEFAULT_CONFIG.parent) / "car.yaml"
    out = Path(out)
    scene = build_scene(sc, config, seconds, seed, world_seed)
    config = scene.config  # with the scenario's camera responses
    rng = np.random.default_rng([seed, 4])
    clocks = drive_clocks(config, sc, rng)
    frame = LocalFrame(sc.origin.latitude_deg, sc.origin.longitude_deg, sc.origin.altitude_m)
    utc0 = utc_start_ns(sc)

    pending: list = []
    counter = itertools.count()

    def push(host_ns: int, topic: str, message: object) -> None:
        heapq.heappush(pending, (host_ns, next(counter), topic, message))

    sensors = config.sensors
    if sensors.gnss is not None:
        fixes_frame = (LocalFrame(*map(float, frame.enu_to_geodetic(np.array(trip.gnss_offset_enu_m))))
                       if visit_number else frame)  # the fixes reported around the offset origin
        for item in _gnss_imu_messages(scene, clocks, fixes_frame, np.random.default_rng([seed, 5])):
            push(*item)
    if sensors.can is not None:
        dbc = resolve_path(config_file, sensors.can.dbc_file)
        for item in _can_messages(scene, clocks, dbc, np.random.default_rng([seed, 6])):
            push(*item)
    for k in range(int(seconds) + 2):
        push(host_mono_ns(k), TIME_ANCHOR, TimeAnchor(sensor_time_ns=host_mono_ns(k), host_mono_ns=host_mono_ns(k),
                                                      utc_ns=utc0 + k * 1_000_000_000))

    _SCENE, _CLOCKS, _MASKS = scene, clocks, masks
    _LIDAR_METADATA = resolve_path(config_file, sensors.lidar.metadata_file) if sensors.lidar else None
    if sensors.lidar is not None and not sensors.lidar.vendor_packets:  # an Ouster's IMU; the Velodynes have none
        for item in _lidar_imu_messages(scene, clocks, np.random.default_rng([seed, 9])):
            push(*item)
    gt_points: list[np.ndarray] = []
    gt_classes: list[np.ndarray] = []
    seq: dict[str, int] = {}
    summary = SimulationSummary(sc.name, seconds, world_seed, out, _gt_path(out))
    metadata = {"start_time_utc_ns": str(utc0), "start_mono_ns": str(HOST_MONO_AT_START_NS),
                "simulator": "sim", "scenario": sc.name, "seed": str(world_seed), "seconds": str(seconds),
                "ground_truth": summary.ground_truth.name, "host": "simulated"}
    if visit_number:
        metadata.update(visit=str(visit_number), drive_seed=str(seed),
                        gnss_offset_enu_m=json.dumps(trip.gnss_offset_enu_m))
    if sc.name not in scenario_names() or visit_number:  # a named scenario is its file in configs/scenarios/
        summary.world = sc.model_dump(mode="json")
        metadata["scenario_yaml"] = scenario_yaml(sc)
    tasks = _tasks(scene, np.random.default_rng([seed, 7]))
    summary.setup_s = time.monotonic() - started
    cam_rng = np.random.default_rng([seed, 8])
    writer = LogWriter(out, config, metadata, config_path=config_file)

    def flush(before_ns: int) -> None:
        while pending and pending[0][0] < before_ns:
            host_ns, _, topic, message = heapq.heappop(pending)
            message.seq = seq.get(topic, 0)
            seq[topic] = message.seq + 1
            message.host_mono_ns = host_ns
            writer.write(topic, message)

    try:
        if workers > 1:
            pool = multiprocessing.get_context("fork").Pool(workers, initializer=_init_worker)
            results = pool.imap(_run_task, tasks, chunksize=1)
        else:
            pool, results = None, map(_run_task, tasks)
        try:
            for result in results:
                if result[0] == "camera":
                    _, ci, fi, true_s, jpeg, png = result
                    cam = sensors.cameras[ci]
                    clock = clocks[f"camera/{cam.name}"]
                    stamp = int(sensor_stamp_ns(clock, np.array([true_s]), cam_rng)[0])
                    host = int(host_arrival_ns(clock, np.array([true_s]), cam_rng)[0])
                    push(host, camera_topic(cam.name), CameraFrame(sensor_time_ns=stamp, camera=cam.name,
                                                                   format="jpeg", data=jpeg))
                    if png is not None:
                        push(host + 4_000_000, mask_topic(cam.name), SemanticMask(sensor_time_ns=stamp,
                                                                                  camera=cam.name, format="png",
                                                                                  data=png))
                    summary.camera_frames += 1
                    event_s = true_s
                else:
                    _, fi, start_s, packets, stamps, arrivals, points, classes = result
                    for p in range(len(packets)):
                        push(int(arrivals[p]), LIDAR_PACKETS, LidarPacket(sensor_time_ns=int(stamps[p]),
                                                                          data=packets[p].tobytes()))
                    if points is not None:
                        gt_points.append(points)
                        gt_classes.append(classes)
                    summary.lidar_scans += 1
                    event_s = start_s
                flush(host_mono_ns(event_s))
        finally:
            if pool is not None:
                pool.close()
                pool.join()
        flush(np.iinfo(np.int64).max)
    finally:
        writer.close({"simulator": "sim"})
    summary.messages = dict(writer.counts)
    summary.bytes_written = out.stat().st_size
    summary.render_s = time.monotonic() - started - summary.setup_s
    _write_ground_truth(scene, frame, summary.ground_truth, gt_points, gt_classes, utc0,
                        metadata.get("scenario_yaml"))
    summary.wall_s = time.monotonic() - started
    summary.ground_truth_s = summary.wall_s - summary.setup_s - summary.render_s
    return summary


def _write_ground_truth(scene: Scene, frame: LocalFrame, path: Path, points: list[np.ndarray],
                        classes: list[np.ndarray], utc0: int, world_yaml: str | None) -> None:
    ego = scene.ego
    s_lo = max(float(ego.s[0]) - 50.0, 0.0)
    s_hi = min(float(ego.s[-1]) + 60.0, scene.world.length_m)
    grids = ground_truth_grids(scene.world, (s_lo, s_hi))
    hits = np.concatenate(points) if points else np.zeros((0, 3), np.float32)
    hit_classes = np.concatenate(classes) if classes else np.zeros(0, np.uint8)
    rows, cols = grids.elevation.shape
    j = np.floor((hits[:, 0] - grids.origin_xy[0]) / grids.resolution).astype(np.int64)
    i = np.floor((hits[:, 1] - grids.origin_xy[1]) / grids.resolution).astype(np.int64)
    inside = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
    inside[inside] = np.isfinite(grids.elevation[i[inside], j[inside]])  # within the mapped corridor
    times = np.arange(0.0, scene.seconds, 1.0 / TRAJECTORY_HZ)
    _, pos = ego.pose(times)
    extra = {} if world_yaml is None else {"scenario_yaml": np.array(world_yaml)}
    np.savez(
        path,
        scenario=np.array(scene.scenario.name),
        seed=np.array(scene.seed),
        enu_origin_lat_lon_alt=np.array([frame.lat_deg, frame.lon_deg, frame.alt_m]),
        grid_origin_xy=np.array(grids.origin_xy),
        grid_resolution_m=np.array(grids.resolution),
        elevation=grids.elevation,
        semantic=grids.semantic,
        albedo=grids.albedo,
        trajectory_host_mono_ns=HOST_MONO_AT_START_NS + np.rint(times * 1e9).astype(np.int64),
        trajectory_position_enu=pos,
        trajectory_quaternion_xyzw=ego.quaternion_xyzw(times),
        lidar_points_enu=hits[inside],
        lidar_points_class=hit_classes[inside],
        host_mono_at_start_ns=np.array(HOST_MONO_AT_START_NS),
        utc_start_ns=np.array(utc0),
        **extra,
    )


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog simulate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", required=True,
                        help="scenario name (configs/scenarios/NAME.yaml), file, or `random` (a world drawn "
                             "from --seed)")
    parser.add_argument("--seconds", type=float, default=None, help="drive length (default: the scenario's)")
    parser.add_argument("--out", type=Path, help="output drive log, PATH.mcap")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="the simulated car's config")
    parser.add_argument("--seed", type=int, default=None,
                        help="override the scenario's seed; with `random`, the world's (default 0)")
    parser.add_argument("--visit", type=int, default=0,
                        help="drive the same world again: visit N > 0 has its own traffic, light, sensor noise and "
                             "GNSS offset (sim/world/revisit.py); 0: the scenario's own drive")
    parser.add_argument("--workers", type=int, default=2, help="rendering processes")
    parser.add_argument("--no-masks", action="store_true",
                        help="leave the segmentation masks out of the log (a car without a segmenter)")
    parser.add_argument("--print-scenario", action="store_true",
                        help="print the scenario (a random world's drawn parameters) as YAML and exit")
    args = parser.parse_args(argv)
    for flag, value, ok, want in (("--seconds", args.seconds, args.seconds is None or args.seconds > 0, "> 0"),
                                  ("--seed", args.seed, args.seed is None or args.seed >= 0, ">= 0"),
                                  ("--workers", args.workers, args.workers >= 1, ">= 1"),
                                  ("--visit", args.visit, args.visit >= 0, ">= 0")):
        if not ok:
            raise ConfigError(f"{flag} {value}: must be {want}")
    config = load_config(args.config)
    if args.print_scenario:
        sc = scenario_for(args.scenario, args.seed, [cam.name for cam in config.sensors.cameras])
        if args.seed is not None:
            sc = sc.model_copy(update={"seed": args.seed})
        print(scenario_yaml(sc), end="")
        return 0
    if args.out is None:
        parser.error("--out is required (unless --print-scenario)")
    if not args.out.parent.is_dir() or args.out.is_dir():  # before the drive is rendered, not after
        raise ConfigError(f"--out {args.out}: " + ("a folder, not a PATH.mcap" if args.out.is_dir() else
                                                   f"no folder {args.out.parent}"))
    sc = scenario_for(args.scenario, args.seed, [cam.name for cam in config.sensors.cameras])  # unknown: exit 2
    if args.seconds is not None and not args.seconds <= sc.max_seconds():  # simulate_drive's ValueError, said first
        raise ConfigError(f"--seconds {args.seconds:g}: scenario {sc.name}'s road allows at most "
                          f"{sc.max_seconds():.1f} s")
    summary = simulate_drive(args.scenario, args.seconds, args.out, config, args.seed,
                             config_dir=args.config.resolve().parent, workers=args.workers,
                             masks=not args.no_masks, visit_number=args.visit)
    print(summary.as_json())
    return 0


if __name__ == "__main__":
    sys.exit(main())
