"""A packet log's drive as a point-cloud Lidar's log, for the tests of the point-cloud path: every Ouster scan decoded
with the driver's own codec (the metadata recorded in the log) into one PointCloud, as an importer writes them."""

from pathlib import Path

import numpy as np
import yaml

from daemon.log_format.reader import read_log, read_metadata
from daemon.log_format.writer import LogWriter
from daemon.spine.config import CarConfig, config_to_yaml, parse_config
from daemon.spine.messages import PointCloud
from daemon.spine.point_cloud_codec import pack_points
from daemon.spine.topics import LIDAR_IMU, LIDAR_PACKETS, LIDAR_POINTS
from drivers.lidar.lidar_points import LidarScan, scan_point_cloud
from drivers.lidar.ouster_decoder import decode_packets, ouster_scan_assembler
from drivers.lidar.ouster_metadata import parse_metadata
from drivers.lidar.ouster_packet_layout import packet_layout
from drivers.lidar.ouster_xyz import make_xyz_lut

# the log's own metadata record keys that the writer makes afresh (the rest, e.g. the simulator's, is kept)
_WRITER_KEYS = {"software_version", "config", "calibration", "lidar_metadata", "host"}


def point_cloud_config(config: CarConfig) -> CarConfig:
    """The car with its Lidar as a point-cloud Lidar (the same mounting, no metadata file)."""
    data = yaml.safe_load(config_to_yaml(config))
    data["sensors"]["lidar"]["model"] = "point-cloud"
    data["sensors"]["lidar"].pop("metadata_file")
    return parse_config(data, "point-cloud config")


def _cloud(scan: LidarScan, lut, seq: int, host_ns: int) -> PointCloud:
    """One scan's points with a return, in column then beam order (as the packets hold them), each at its column's
    time, the scan starting at its first column's."""
    points = scan_point_cloud(scan, lut)
    order = np.lexsort((points.ring, points.column))
    start = int(scan.timestamp_ns[scan.column_valid].min())
    time_s = (points.timestamp_ns[order].astype(np.int64) - start) / 1e9
    data = pack_points(points.xyz[order], points.reflectivity[order], time_s)
    return PointCloud(seq=seq, sensor_time_ns=start, host_mono_ns=host_ns, sensor="lidar", data=data)


def point_cloud_log(packet_log: Path, out: Path) -> Path:
    """`packet_log` rewritten into `out` with its Lidar packets as point clouds (each at the arrival of its scan's
    last packet), the Lidar's IMU dropped (a point-cloud Lidar has none) and every other message as it was."""
    recorded = read_metadata(packet_log)["roadlog"]
    config = point_cloud_config(parse_config(yaml.safe_load(recorded["config"])))
    metadata = parse_metadata(recorded["lidar_metadata"])
    layout, lut = packet_layout(metadata), make_xyz_lut(metadata)
    assembler = ouster_scan_assembler(layout)
    kept = {k: v for k, v in recorded.items() if k not in _WRITER_KEYS}
    seq = 0
    with LogWriter(out, config, kept) as writer:
        last_ns = 0
        for record in read_log([packet_log]):
            if record.topic == LIDAR_PACKETS:
                last_ns = record.log_time_ns
                for scan in assembler.add(decode_packets([bytes(record.message.data)], layout)):
                    writer.write(LIDAR_POINTS, _cloud(scan, lut, seq, last_ns))
                    seq += 1
            elif record.topic != LIDAR_IMU:
                writer.write(record.topic, record.message)
        for scan in assembler.flush():
            writer.write(LIDAR_POINTS, _cloud(scan, lut, seq, last_ns))
    return out
