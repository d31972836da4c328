"""What one window of the live mapping worker (mapping.live.worker_loop) is optimised from, and its gathering from
the worker's spools."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from daemon.spine.topics import (
    FUSION_TOPICS,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    TIME_ANCHOR,
    camera_topic,
    mask_topic,
)
from mapping.inputs.drive_inputs import (
    camera_pose,
    decode_image,
    keyframe_semantics,
    spaced_camera_frames,
)
from mapping.inputs.lidar_ground import GroundFilter, lidar_scans, scans_ground
from mapping.live.window_schedule import window_span
from mapping.localization.sensor_time import span_clock
from mapping.localization.trajectory import HorizontalTrack, Trajectory
from mapping.method.scene_data import Keyframe, StandingPoints

if TYPE_CHECKING:
    from mapping.live.worker_loop import MappingWorker

FUSION_MARGIN_S = 20.0  # a window's fusion starts this long before it (and what is spooled is kept that far back)
INPUT_HORIZON_NS = 2_000_000_000  # a window's inputs reach this far past its end (fusion; clocks 1 s)


@dataclass
class WindowInputs:
    """What one window is optimised from, gathered from the spool and the small streams."""

    centre_m: float  # the window's centre, start and end along the drive (end clipped to the distance driven)
    start_m: float
    end_m: float
    t_lo_ns: int  # the host time span the window covers (within the fused trajectory)
    t_hi_ns: int
    trajectory: Trajectory  # fused over the small streams held, up to t_hi_ns + INPUT_HORIZON_NS
    path: HorizontalTrack  # the window's track: times in seconds from t_lo_ns
    keyframes: list[Keyframe]
    ground: np.ndarray | None  # Lidar ground points, None without a Lidar
    ground_times: np.ndarray | None  # each ground point's firing time, s from t_lo_ns (the pose refinement's
    # Lidar registration re-places the points with them, as `reconstruct` does offline)
    provenance: dict  # host time range, per-topic seq ranges, log segments, input counts (into the journal)
    standing: StandingPoints | None  # what the Lidar saw standing on the road, for keyframes without masks
    ground_contrast: np.ndarray | None = None  # each ground point's intensity contrast (the registration's)


def gather_window_inputs(worker: MappingWorker, k: int) -> WindowInputs:
    """Window k's inputs: its span by the odometry, the trajectory fused over it (from FUSION_MARGIN_S before),
    its keyframes, Lidar ground and provenance, from the worker's spools."""
    m = worker.mapper
    centre, s_lo, s_hi = window_span(k, m.windows.before_m, m.windows.after_m)
    s_hi = min(s_hi, worker.state.distance_m)
    t_lo, t_hi = worker.odometry.time_at(s_lo), worker.odometry.time_at(s_hi)
    horizon = t_hi + INPUT_HORIZON_NS
    small = worker.reader.read_small(t_lo - int(FUSION_MARGIN_S * 1e9), horizon)
    traj = worker.fuse(small)
    if traj is None:
        raise ValueError("not enough GNSS/IMU/wheel data for the window")
    t_lo, t_hi = max(t_lo, int(traj.times_ns[0])), min(t_hi, int(traj.times_ns[-1]))
    if t_hi - t_lo < 1e8:
        raise ValueError(f"window {k}: trajectory covers only [{traj.times_ns[0]}, {traj.times_ns[-1]}]")
    cams = [c.name for c in worker.config.sensors.cameras]
    want = {camera_topic(c) for c in cams} | {mask_topic(c) for c in cams}
    if worker.config.sensors.lidar is not None:
        want |= {LIDAR_PACKETS, LIDAR_POINTS}
    with worker.lock:
        records = list(worker.spool.read(t_lo - 1_000_000_000, t_hi + 1_000_000_000, want))
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
    for cam in worker.config.sensors.cameras:
        masks = {x.sensor_time_ns: x for x in by_topic.get(mask_topic(cam.name), [])}
        frames = sorted(by_topic.get(camera_topic(cam.name), []), key=lambda f: f.sensor_time_ns)
        if not frames:
            continue
        host = clocks[camera_topic(cam.name)].to_host([f.sensor_time_ns for f in frames])
        inside = [(f, int(t)) for f, t in zip(frames, host, strict=True) if t_lo <= t <= t_hi]
        frames_seen += len(inside)
        frames_without_mask += 0 if worker.segmenter else sum(f.sensor_time_ns not in masks for f, _ in inside)
        chosen = spaced_camera_frames(inside, None if worker.segmenter else masks, traj, m.inputs.keyframe_spacing_m)
        for f, t, mask in chosen:
            image = decode_image(f)
            keyframes.append(Keyframe(cam.name, (t - t_lo) / 1e9, camera_pose(traj, t, cam.extrinsics.matrix()),
                                      image, keyframe_semantics(image, mask, worker.segmenter)))
    keyframes.sort(key=lambda kf: kf.timestamp)
    scans = lidar_scans(by_topic.get(LIDAR_PACKETS, []), by_topic.get(LIDAR_POINTS, []),
                        lambda: worker.lidar_decoding, 1)  # every n-th scan: kept by the bus thread
    ground = ground_times = standing = contrast = None
    if scans is not None:  # what stands on the road too, when a keyframe has no mask to leave it out
        occlusion = m.maskless.lidar_occlusion and any(kf.semantics is None for kf in keyframes)
        ground, ground_times, standing, contrast = scans_ground(
            scans, clocks[scans.topic], worker.config, traj,
            GroundFilter(corridor_half_width_m=m.mesh.corridor_half_width_m), t_lo if occlusion else None)
        ground_times = ground_times + (int(traj.times_ns[0]) - t_lo) / 1e9  # from the fusion's start to t_lo's
    fed = dict(by_topic)
    for t in FUSION_TOPICS:
        fed[t] = [x for x in small[t] if t_lo <= x.host_mono_ns <= t_hi]
    seq = {t: [min(x.seq for x in v), max(x.seq for x in v)] for t, v in sorted(fed.items()) if v}
    provenance = {"host_time_ns": [t_lo, t_hi], "seq": seq,
                  "segments": sorted(n for n, (a, b) in worker.reader.segments.items() if a <= t_hi and b >= t_lo),
                  "keyframes": len(keyframes), "frames": frames_seen, "frames_without_mask": frames_without_mask,
                  **(scans.counts if scans else {"lidar_packets": 0}),
                  "lidar_ground_points": 0 if ground is None else len(ground)}
    return WindowInputs(centre, s_lo, s_hi, t_lo, t_hi, traj, path, keyframes, ground, ground_times, provenance,
                        standing, contrast)
