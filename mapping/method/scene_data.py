"""In-memory inputs of the road-surface reconstruction: cameras, keyframes, the Lidar's standing points, ground
truth (the trajectory they go with: mapping.localization.trajectory.HorizontalTrack).

Frames: world is metric with z up; camera axes follow OpenCV (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera with OpenCV radial-tangential distortion (k1 k2 p1 p2 k3)."""

    name: str
    K: np.ndarray  # 3x3 intrinsic matrix
    distortion: tuple[float, float, float, float, float]
    width: int
    height: int
    mount_rotation: np.ndarray | None = None  # 3x3 camera -> vehicle rotation of its extrinsics; None: unknown

    @property
    def distorted(self) -> bool:
        return any(d != 0.0 for d in self.distortion)


@dataclass(frozen=True)
class Keyframe:
    """One camera image with its pose and segmentation (if it has one)."""

    camera: str  # CameraModel.name
    timestamp: float  # seconds, same clock as HorizontalTrack.times
    T_world_camera: np.ndarray  # 4x4, camera (OpenCV axes) to world
    image: np.ndarray  # HxWx3 uint8 RGB
    semantics: np.ndarray | None  # HxW uint8 ids of daemon.spine.semantic_classes.SemanticClass; None: no mask and
    # no segmentation model (the keyframe gives colour and elevation only)


@dataclass(frozen=True)
class GroundTruth:
    """True rasters of a simulated drive: elevation (NaN = unknown) and, where known, semantic class ids on the
    same grid; cell (i, j) is centred at (x0 + j*res, y0 + i*res)."""

    elevation_m: np.ndarray  # (H, W) float
    origin_xy: tuple[float, float]  # centre of cell (0, 0)
    resolution_m: float
    semantic: np.ndarray | None = None  # (H, W) uint8 class ids (>= NUM_MAP_CLASSES: no map class)


@dataclass(frozen=True)
class StandingPoints:
    """Lidar points of things standing on the road (cars, people, walls: mapping.inputs.lidar_ground
    .standing_points), scan by scan: scan k holds points[starts[k]:starts[k + 1]], its middle at times[k]."""

    times: np.ndarray  # (S,) float64 seconds, same clock as Keyframe.timestamp, increasing
    starts: np.ndarray  # (S + 1,) int64
    points: np.ndarray  # (M, 3) float32 world

    @staticmethod
    def of(scans: list[tuple[float, np.ndarray]]) -> StandingPoints:
        """From (time, (n, 3) points) per scan, in time order."""
        sizes = [len(p) for _, p in scans]
        return StandingPoints(np.array([t for t, _ in scans], np.float64),
                              np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                              np.concatenate([p for _, p in scans]).astype(np.float32) if scans
                              else np.zeros((0, 3), np.float32))

    def nearest_scan(self, time_s: float, max_gap_s: float) -> np.ndarray | None:
        """The points of the scan nearest in time to `time_s`, None when none is within `max_gap_s`."""
        if not len(self.times):
            return None
        k = int(np.clip(np.searchsorted(self.times, time_s), 1, len(self.times)) - 1)
        if k + 1 < len(self.times) and abs(self.times[k + 1] - time_s) < abs(self.times[k] - time_s):
            k += 1
        if abs(self.times[k] - time_s) > max_gap_s:
            return None
        return self.points[self.starts[k]:self.starts[k + 1]]
