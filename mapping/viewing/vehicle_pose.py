"""The `vehicle_pose` process: the vehicle's pose fused live from the bus's GNSS fixes, IMU samples and wheel speeds,
published `recorder.pose_hz` times a second of drive on `vehicle/pose` for the log (foxglove.PoseInFrame, and the
recorder's `tf` transform map -> vehicle), so the car moves in Foxglove's 3D panel, in a live run and in a replay.

It fuses as the live mapping worker does (`drive_inputs.fuse_bus_trajectory`: the ESKF and RTS smoother of
`pose_fusion`, each sensor's clock spanned onto the host clock), over the last FUSION_WINDOW_S of data, every
FUSE_EVERY_S of drive, and once more when it is stopped (the supervisor stops it after the drivers, before the
recorder); the poses from the last one published up to the newest fused time (less END_MARGIN_S, where the
smoother has seen little past them, but at the stop) come out on a grid of host times 1/pose_hz apart, each stamped
(sensor_time_ns and host_mono_ns) at the time it is the pose of: on the host clock, as the camera frames are. The map
frame (`map`) is local ENU at the first GNSS fix this process received; that origin (latitude, longitude in degrees,
ellipsoidal height in metres) is in every health report's detail (`map_origin`), which the recorder logs once a second,
so each segment places its `map` frame on the earth. A fusion that fails (too few fixes, a gap)
is counted and retried with the next data; nothing is published for the span it could not fuse.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np

from daemon.spine.config import CarConfig, reports_config_errors
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import VehiclePose
from daemon.spine.topics import (
    FUSION_TOPICS,
    GNSS_FIX,
    IMU,
    MAP_FRAME,
    TIME_ANCHOR,
    VEHICLE_POSE,
    VEHICLE_POSE_PROCESS,
    fuses_pose,
)
from mapping.inputs.drive_inputs import fuse_bus_trajectory
from mapping.viewing.viewing_process import serve, viewing_main

FUSION_WINDOW_S = 8.0  # data fused each time (the first GNSS fix of it is where the filter starts)
FUSE_EVERY_S = 1.0  # of drive (the newest IMU sample's host time) between two fusions: one takes ~0.3 s of a core
END_MARGIN_S = 0.2  # poses this close to the newest fused time wait for the next fusion
MIN_FIXES, MIN_IMU = 5, 20


class LivePose:
    """The bus's GNSS, IMU, wheel speeds and time anchors in, poses out (see the module docstring)."""

    def __init__(self, config: CarConfig):
        self.config = config
        self.step_ns = int(round(1e9 / config.recorder.pose_hz))
        self.held: dict[str, list] = {t: [] for t in (*FUSION_TOPICS, TIME_ANCHOR)}
        self.origin: LocalFrame | None = None
        self.next_ns: int | None = None  # host time of the next pose to publish
        self.fused_at_ns = 0  # the newest IMU time of the last fusion
        self.fusions = self.failed = 0
        self.last_error = ""
        self.lag_s = self.max_lag_s = 0.0  # how long after its time the oldest pose of the last fusion went out

    def take(self, topic: str, msg: object) -> None:
        self.held[topic].append(msg)
        if topic == GNSS_FIX and self.origin is None:
            self.origin = LocalFrame(msg.latitude_deg, msg.longitude_deg, msg.altitude_m)

    def poses(self, final: bool = False) -> list[VehiclePose]:
        """The poses due, once FUSE_EVERY_S of drive has come since the last fusion (else none); `final` (the data
        has ended): at once, up to the newest fused time."""
        imu = self.held[IMU]
        if self.origin is None or not imu or (
                not final and imu[-1].host_mono_ns - self.fused_at_ns < FUSE_EVERY_S * 1e9):
            return []
        newest = int(imu[-1].host_mono_ns)
        self.fused_at_ns = newest
        start = newest - int(FUSION_WINDOW_S * 1e9)
        for topic in FUSION_TOPICS:
            self.held[topic] = [m for m in self.held[topic] if m.host_mono_ns >= start]
        if len(self.held[GNSS_FIX]) < MIN_FIXES or len(self.held[IMU]) < MIN_IMU:
            return []
        try:
            trajectory = fuse_bus_trajectory(self.held, self.config, self.origin)
        except (ValueError, np.linalg.LinAlgError) as exc:  # a gap or a bad stretch: the next data may fuse
            self.failed += 1
            self.last_error = f"fusion over {len(self.held[GNSS_FIX])} fixes: {exc}"
            return []
        self.fusions += 1
        margin_ns = 0 if final else int(END_MARGIN_S * 1e9)
        first, last = int(trajectory.times_ns[0]), int(trajectory.times_ns[-1]) - margin_ns
        if self.next_ns is None or self.next_ns < first:  # the first poses, or after a span that did not fuse
            self.next_ns = -(-first // self.step_ns) * self.step_ns
        times = np.arange(self.next_ns, last + 1, self.step_ns, dtype=np.int64)
        if not len(times):
            return []
        self.next_ns = int(times[-1]) + self.step_ns
        positions, quaternions = trajectory.interpolate(times)
        return [VehiclePose(sensor_time_ns=int(t), host_mono_ns=int(t), frame_id=MAP_FRAME,
                            position_m=tuple(map(float, p)), orientation_xyzw=tuple(map(float, q)))
                for t, p, q in zip(times, positions, quaternions, strict=True)]

    def report(self) -> dict[str, object]:
        origin = None if self.origin is None else {
            "lat_deg": self.origin.lat_deg, "lon_deg": self.origin.lon_deg, "alt_m": self.origin.alt_m}
        return {"fusions": self.fusions, "failed": self.failed, "lag_s": round(self.lag_s, 3),
                "max_lag_s": round(self.max_lag_s, 3), "last_error": self.last_error, "map_origin": origin}


def run(config: CarConfig, stop: threading.Event) -> LivePose:
    """Publish live poses until `stop` is set."""
    pose = LivePose(config)

    def step(read: list, final: bool) -> list[VehiclePose]:
        for topic, msg in read:
            pose.take(topic, msg)
        poses = pose.poses(final)
        if poses and not final:
            pose.lag_s = (time.monotonic_ns() - poses[0].host_mono_ns) / 1e9
            pose.max_lag_s = max(pose.max_lag_s, pose.lag_s)
        return poses

    serve(config, VEHICLE_POSE_PROCESS, [*FUSION_TOPICS, TIME_ANCHOR], VEHICLE_POSE, step,
          lambda: (pose.failed, pose.report()), stop)
    return pose


def _run_summary(config: CarConfig, _config_path: str, stop: threading.Event) -> str:
    pose = run(config, stop)
    return f"{pose.fusions} fusions, {pose.failed} failed, poses out at most {pose.max_lag_s:.2f} s after their time"


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    return viewing_main(argv, VEHICLE_POSE_PROCESS, "roadlog vehicle-pose", __doc__.split("\n\n")[0], fuses_pose,
                        "no live pose to fuse (sensors.gnss and recorder.pose_hz > 0)", _run_summary)


if __name__ == "__main__":
    sys.exit(main())
