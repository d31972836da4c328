"""Lidar ground points for the elevation loss: raw packets -> world points -> ground points only.

Points are moved into the world frame column by column with the vehicle pose at each column's time
(motion compensated). The ground filter keeps points within a height band around the trajectory's
ground height at the nearest trajectory point, then, on a 0.5 m grid, only points close to the lowest
point of their cell: points on cars and other things standing on the road are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from drivers.lidar.lidar_points import XYZLut, batch_xyz
from drivers.lidar.ouster_decoder import decode_packets
from drivers.lidar.ouster_metadata import OusterMetadata
from drivers.lidar.ouster_packet_layout import OusterPacketLayout, packet_layout
from drivers.lidar.ouster_xyz import make_xyz_lut
from mapping.sensor_time import ClockMap
from mapping.trajectory import Trajectory


@dataclass(frozen=True)
class GroundFilter:
    max_range_m: float = 40.0
    min_range_m: float = 2.0
    band_m: float = 0.35  # kept when within this of the trajectory ground height
    corridor_half_width_m: float = 15.0
    cell_m: float = 0.5
    above_cell_min_m: float = 0.08  # kept when within this of the lowest point of its grid cell
    voxel_m: float = 0.1  # at most one point per voxel of this size (per scan)


@dataclass(frozen=True)
class LidarDecoding:
    """What decoding one sensor's packets needs, built once per drive."""

    layout: OusterPacketLayout
    lut: XYZLut

    @staticmethod
    def of(metadata: OusterMetadata) -> LidarDecoding:
        return LidarDecoding(packet_layout(metadata), make_xyz_lut(metadata))


def lidar_world_points(packets: list[bytes], clock: ClockMap, decoding: LidarDecoding,
                       T_vehicle_lidar: np.ndarray, trajectory: Trajectory, settings: GroundFilter) -> np.ndarray:
    """World points (N, 3) of one batch of packets, motion compensated; columns outside the trajectory dropped."""
    layout, lut = decoding.layout, decoding.lut
    batch = decode_packets(packets, layout)
    if batch.num_packets == 0:
        return np.zeros((0, 3))
    xyz = batch_xyz(batch, lut).astype(np.float64)  # (P, K, H, 3) sensor frame, metres
    rng = batch.range_mm.astype(np.float64) / 1000.0
    ok = batch.column_valid[..., None] & (rng > settings.min_range_m) & (rng < settings.max_range_m)
    times = clock.to_host(batch.timestamp_ns.astype(np.int64).ravel()).reshape(batch.timestamp_ns.shape)  # (P, K)
    inside = (times >= trajectory.times_ns[0]) & (times <= trajectory.times_ns[-1])
    ok &= inside[..., None]
    if not ok.any():
        return np.zeros((0, 3))
    col_times = times[inside]
    positions, quats = trajectory.interpolate(col_times)
    from scipy.spatial.transform import Rotation

    R_world_vehicle = Rotation.from_quat(quats).as_matrix()  # (C, 3, 3)
    pts = xyz[inside]  # (C, H, 3)
    keep = ok[inside]  # (C, H)
    pts_vehicle = pts @ T_vehicle_lidar[:3, :3].T + T_vehicle_lidar[:3, 3]
    world = np.einsum("cij,chj->chi", R_world_vehicle, pts_vehicle) + positions[:, None, :]
    return world[keep]


@dataclass(frozen=True)
class TrajectoryGround:
    """The road height under the trajectory, with a 2-D index to find the nearest point (built once per drive)."""

    ground: np.ndarray  # (N, 3) trajectory points moved down to the road
    tree: cKDTree

    @staticmethod
    def of(trajectory: Trajectory, reference_height_m: float) -> TrajectoryGround:
        ground = trajectory.positions.copy()
        ground[:, 2] -= reference_height_m
        return TrajectoryGround(ground, cKDTree(ground[:, :2]))


def _first_per_cell(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first index, inverse) of the distinct rows of an int64 cell array, through one int64 key per row."""
    key = np.zeros(len(cells), np.int64)
    for k in range(cells.shape[1]):
        key = key * 2_000_003 + (cells[:, k] + 1_000_001)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return first, inverse.ravel()


def ground_points(world: np.ndarray, road: TrajectoryGround, settings: GroundFilter) -> np.ndarray:
    """The points of `world` that lie on the road surface (see the module docstring)."""
    if len(world) == 0:
        return world
    ground = road.ground
    dist, idx = road.tree.query(world[:, :2])
    near = (dist < settings.corridor_half_width_m) & (np.abs(world[:, 2] - ground[idx, 2]) < settings.band_m)
    pts = world[near]
    if len(pts) == 0:
        return pts
    _, inverse = _first_per_cell(np.floor(pts[:, :2] / settings.cell_m).astype(np.int64))
    cell_min = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(cell_min, inverse, pts[:, 2])
    pts = pts[pts[:, 2] - cell_min[inverse] < settings.above_cell_min_m]
    first, _ = _first_per_cell(np.floor(pts / settings.voxel_m).astype(np.int64))
    return pts[np.sort(first)]
