"""Ouster XYZ lookup table (the Ouster SDK formulation): per (column, beam) direction and offset
that turn a range in millimetres into a point in metres in the sensor frame."""

from __future__ import annotations

import numpy as np

from drivers.lidar.lidar_points import XYZLut
from drivers.lidar.ouster_metadata import OusterMetadata

RANGE_UNIT_M = 0.001


def make_xyz_lut(meta: OusterMetadata, sensor_to_body: np.ndarray | None = None) -> XYZLut:
    """LUT for the sensor frame, or for the body frame when `sensor_to_body` (4x4, metres) is given.

    The beam leaves the lidar origin's circle of radius |beam_to_lidar translation| at the
    encoder angle, pointing along encoder angle + beam azimuth offset and the beam altitude; the
    lidar_to_sensor transform then maps lidar into sensor coordinates."""
    w = meta.columns_per_frame
    beam_to_lidar = meta.beam_to_lidar_transform
    radius_mm = float(np.hypot(beam_to_lidar[0, 3], beam_to_lidar[2, 3]))
    encoder = 2.0 * np.pi - np.arange(w)[:, None] * (2.0 * np.pi / w)  # (W, 1)
    azimuth = -np.radians(meta.beam_azimuth_angles)[None, :]  # (1, H)
    altitude = np.radians(meta.beam_altitude_angles)[None, :]
    direction = np.stack(
        np.broadcast_arrays(
            np.cos(encoder + azimuth) * np.cos(altitude),
            np.sin(encoder + azimuth) * np.cos(altitude),
            np.sin(altitude),
        )
    )  # (3, W, H)
    offset = np.stack(
        np.broadcast_arrays(
            np.cos(encoder) * beam_to_lidar[0, 3] - direction[0] * radius_mm,
            np.sin(encoder) * beam_to_lidar[0, 3] - direction[1] * radius_mm,
            -direction[2] * radius_mm + beam_to_lidar[2, 3],
        )
    )
    transform = meta.lidar_to_sensor_transform.copy()
    if sensor_to_body is not None:
        to_body = np.asarray(sensor_to_body, dtype=np.float64).copy()
        to_body[:3, 3] /= RANGE_UNIT_M
        transform = to_body @ transform
    rotation, translation = transform[:3, :3], transform[:3, 3]
    direction = np.einsum("ij,jwh->iwh", rotation, direction)
    offset = np.einsum("ij,jwh->iwh", rotation, offset) + translation[:, None, None]
    return XYZLut(
        direction=np.ascontiguousarray(direction * RANGE_UNIT_M, dtype=np.float32),
        offset=np.ascontiguousarray(offset * RANGE_UNIT_M, dtype=np.float32),
    )
