"""The point records of a `PointCloud` message: packed little-endian float32 (x, y, z, intensity, time_s), 20 bytes a
point, defined once here for the importers that write them, the log format and the mapper that read them."""

from __future__ import annotations

import numpy as np

from daemon.spine.messages import PointCloud

POINT_FIELDS = ("x", "y", "z", "intensity", "time")  # in this order, float32 each, at offsets 0, 4, 8, 12, 16
POINT_STRIDE = 4 * len(POINT_FIELDS)  # bytes per point
_RECORD = np.dtype("<f4")


def pack_points(xyz: np.ndarray, intensity: np.ndarray | None = None, time_s: np.ndarray | None = None) -> bytes:
    """The `data` of a PointCloud: (N, 3) points in the Lidar frame (metres), their intensity (N,) and firing time
    (N,) in seconds after the message's sensor_time_ns; a missing intensity or time is 0 for every point."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {xyz.shape}")
    records = np.zeros((len(xyz), len(POINT_FIELDS)), _RECORD)
    records[:, :3] = xyz
    for column, values in ((3, intensity), (4, time_s)):
        if values is not None:
            values = np.asarray(values).reshape(-1)
            if len(values) != len(xyz):
                raise ValueError(f"{POINT_FIELDS[column]} has {len(values)} values for {len(xyz)} points")
            records[:, column] = values
    return records.tobytes()


def point_array(cloud: PointCloud) -> np.ndarray:
    """The cloud's points as a read-only (N, 5) float32 array of (x, y, z, intensity, time_s) rows, without a copy."""
    data = cloud.data
    if len(data) % POINT_STRIDE:
        raise ValueError(f"point cloud {cloud.seq} of {cloud.sensor!r}: {len(data)} bytes is not a whole number of "
                         f"{POINT_STRIDE}-byte points")
    return np.frombuffer(data, _RECORD).reshape(-1, len(POINT_FIELDS))
