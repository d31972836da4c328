"""The `lidar_view` process: one Lidar scan decoded into points every 1/`recorder.point_cloud_view_hz` s, published on
`lidar/view` for the log, so Foxglove's 3D panel shows the point cloud (the raw packets stay the lossless record).

The packets are grouped into scans as the mapper numbers them (`lidar_ground.scan_number`: an Ouster's
`packets_per_frame` at a time, a vendor Lidar's by rotation period) and decoded by the mapper's own decoders
(`lidar_ground.scan_decoder`: the Ouster codec or the configured vendor decoder, every model the mapper reads); only
the scans that are due are decoded. A viewing cloud is in the Lidar's frame (`lidar`, as `tf_static` names it),
without the points that had no return (a scan with none is counted and skipped) and without motion compensation (as
a driver's cloud), and stamped on the host clock as the camera frames are: each packet's stamp moved by the smallest
(host arrival - stamp) of the last scans, the transport latency. Its host_mono_ns is its first point's time, so the
log places it with the frames of that moment. A scan that does not decode is counted and skipped. The mapper never
reads `lidar/view`; `roadlog reconstruct` takes it only from a log that holds no packets and no `lidar/points`.
"""

from __future__ import annotations

import sys
import threading
from collections import deque

import numpy as np

from daemon.log_format.static_transforms import LIDAR_FRAME
from daemon.spine.config import CarConfig, reports_config_errors
from daemon.spine.messages import LidarPacket, PointCloud
from daemon.spine.point_cloud_codec import pack_points
from daemon.spine.topics import LIDAR_PACKETS, LIDAR_VIEW, LIDAR_VIEW_PROCESS, views_lidar
from drivers.lidar.ouster_metadata import OusterMetadata
from mapping.inputs.lidar_ground import VendorDecoding, configured_decoding, scan_decoder, scan_number
from mapping.viewing.viewing_process import serve, viewing_main

LATENCY_SCANS = 100  # the transport latency is the smallest of this many scans' (host - stamp)


class ViewingClouds:
    """A Lidar's packets in, now and then a viewing cloud out (see the module docstring)."""

    def __init__(self, decoding: OusterMetadata | VendorDecoding, view_hz: float, lidar_hz: float):
        self.decoding = decoding
        self.decode = scan_decoder(decoding)
        # a scan is due this long after the last one viewed (half a scan early: scans start where they fall)
        self.period_ns = int(1e9 / view_hz - 0.5e9 / lidar_hz)
        self.packets: list[LidarPacket] = []
        self.scan: int | None = None
        self.lead: LidarPacket | None = None  # the packet before the scan being gathered
        self.count = 0
        self.latency_ns: deque[int] = deque(maxlen=LATENCY_SCANS)
        self.last_view_ns: int | None = None
        self.scans = self.viewed = self.undecodable = self.without_points = 0
        self.last_error = ""

    def take(self, packet: LidarPacket) -> PointCloud | None:
        """One packet, in arrival order; the viewing cloud of the scan it ends, when that scan was due."""
        number = scan_number(self.decoding, LIDAR_PACKETS, self.count, packet)
        self.count += 1
        cloud = None
        if self.scan is not None and number != self.scan:
            cloud = self._finish()
        self.scan = number
        self.packets.append(packet)
        return cloud

    def _finish(self) -> PointCloud | None:
        packets, self.packets = self.packets, []
        lead, self.lead = self.lead, packets[-1]
        self.scans += 1
        self.latency_ns.append(min(int(p.host_mono_ns) - int(p.sensor_time_ns) for p in packets))
        start_ns = int(packets[0].host_mono_ns)
        if self.last_view_ns is not None and start_ns - self.last_view_ns < self.period_ns:
            return None
        self.last_view_ns = start_ns
        try:
            points = self.decode(lead, packets)
        except (ValueError, IndexError) as exc:  # packets the driver let through that still do not decode
            self.undecodable += 1
            self.last_error = f"scan of {len(packets)} packets from seq {packets[0].seq}: {exc}"
            return None
        returned = np.flatnonzero(np.any(points.xyz != 0, axis=1))
        if not len(returned):  # a blocked sensor, or packets its decoder rejects whole
            self.without_points += 1
            return None
        host_ns = points.times_ns[points.time_index[returned]] + min(self.latency_ns)
        first = int(host_ns.min())
        self.viewed += 1
        data = pack_points(points.xyz[returned],
                           None if points.intensity is None else points.intensity[returned],
                           (host_ns - first) / 1e9)
        return PointCloud(sensor_time_ns=first, host_mono_ns=first, sensor=LIDAR_FRAME, data=data)

    def report(self) -> dict[str, int | str]:
        return {"scans": self.scans, "viewed": self.viewed, "undecodable": self.undecodable,
                "without_points": self.without_points, "last_error": self.last_error}


def check_config(car: CarConfig, config_path: str) -> None:
    """Its start-up check (also run by `roadlog check-config`): the Lidar's metadata or calibration reads and fits
    its model (ConfigError naming the file otherwise)."""
    configured_decoding(car.sensors.lidar, config_path)


def run(config: CarConfig, config_path: str, stop: threading.Event) -> ViewingClouds:
    """Publish viewing clouds until `stop` is set."""
    lidar = config.sensors.lidar
    viewer = ViewingClouds(configured_decoding(lidar, config_path), config.recorder.point_cloud_view_hz, lidar.rate_hz)

    def step(read: list, final: bool) -> list[PointCloud]:
        return [cloud for _, packet in read if (cloud := viewer.take(packet)) is not None]

    serve(config, LIDAR_VIEW_PROCESS, [LIDAR_PACKETS], LIDAR_VIEW, step,
          lambda: (viewer.undecodable, viewer.report()), stop)
    return viewer


def _run_summary(config: CarConfig, config_path: str, stop: threading.Event) -> str:
    viewer = run(config, config_path, stop)
    return f"{viewer.scans} scans, {viewer.viewed} viewed, {viewer.undecodable} undecodable"


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    return viewing_main(argv, LIDAR_VIEW_PROCESS, "roadlog lidar-view", __doc__.split("\n\n")[0], views_lidar,
                        "no viewing clouds to make (a Lidar that sends packets and recorder.point_cloud_view_hz > 0)",
                        _run_summary)


if __name__ == "__main__":
    sys.exit(main())
