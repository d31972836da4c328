"""In-memory inputs of the road-surface reconstruction: cameras, keyframes, ground truth (the trajectory they go
with: mapping.localization.trajectory.HorizontalTrack).

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
