"""What hides the road in a view without a mask: the Lidar's points standing on the road (cars, people, walls:
mapping.inputs.lidar_ground.standing_points) in the scan nearest in time to the view, as an occlusion test.

A mask marks a car's pixels as an obstacle and the fits leave them out; a view without one would paint the car
into the road behind it. The standing points of the scan nearest in time are projected into the view and kept,
per image cell of `cell_px` pixels, as the nearest one's depth; each cell then takes the nearest of itself and
its two neighbours across (the Lidar's columns are sparser than the pixels) and of every cell above it in its
column: a thing standing on the ground hides everything between its top and its foot, and its foot is below
its points in the image. A surface point is hidden in the view when its cell holds a standing point nearer than
it by more than `margin_m`. Nearer ground (in front of the car) is not: it is nearer than the car.

What it rejects: whatever the Lidar saw standing on the road when the camera took the view, moving or not. What
it cannot: what the Lidar did not see (beyond its range, below its field of view close to the car, a thing
that moved further than the margin between the scan and the view), and what lies on the road (the shadow of a
moving car, a puddle's reflection): those reach the colours as in any view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemon.spine.mapper_config import MasklessConfig
from mapping.fits.vertex_observations import project_points
from mapping.method.scene_data import CameraModel, Keyframe, StandingPoints


@dataclass(frozen=True)
class OcclusionTest:
    """The standing points of a drive and the test's settings (`mapper.maskless`)."""

    standing: StandingPoints
    settings: MasklessConfig

    @staticmethod
    def of(standing: StandingPoints | None, settings: MasklessConfig) -> OcclusionTest | None:
        """The test, None when there are no standing points (no Lidar) or it is switched off."""
        return OcclusionTest(standing, settings) if standing is not None and settings.lidar_occlusion else None

    def nearest_depths(self, keyframe: Keyframe, camera: CameraModel) -> np.ndarray | None:
        """(rows, columns) of image cells: the depth of the nearest standing point hiding each cell (inf: none),
        None when no Lidar scan lies within `max_gap_s` of the view."""
        points = self.standing.nearest_scan(keyframe.timestamp, self.settings.max_gap_s)
        if points is None:
            return None
        cell = self.settings.cell_px
        shape = (camera.height // cell + 1, camera.width // cell + 1)
        nearest = np.full(shape, np.inf)
        if len(points):
            uv, ok = project_points(points.astype(np.float64), camera, keyframe.T_world_camera)
            depth = _depth(points[ok], keyframe)
            np.minimum.at(nearest, ((uv[ok, 1] // cell).astype(np.int64), (uv[ok, 0] // cell).astype(np.int64)),
                          depth)
        across = nearest.copy()
        across[:, 1:] = np.minimum(across[:, 1:], nearest[:, :-1])
        across[:, :-1] = np.minimum(across[:, :-1], nearest[:, 1:])
        return np.minimum.accumulate(across, axis=0)  # and every cell above: it stands on the ground

    def hidden(self, keyframe: Keyframe, camera: CameraModel, uv: np.ndarray,
               points_world: np.ndarray) -> np.ndarray | None:
        """(M,) bool: which surface points (world `points_world`, seen at pixels `uv` inside the image) something
        standing on the road hides in this view; None when no Lidar scan lies within `max_gap_s` of it."""
        nearest = self.nearest_depths(keyframe, camera)
        if nearest is None:
            return None
        cell = self.settings.cell_px
        behind = nearest[(uv[:, 1] // cell).astype(np.int64), (uv[:, 0] // cell).astype(np.int64)]
        return behind < _depth(points_world, keyframe) - self.settings.margin_m


def _depth(points_world: np.ndarray, keyframe: Keyframe) -> np.ndarray:
    """Depth along the optical axis of world points in the keyframe's camera."""
    T = keyframe.T_world_camera
    return (np.asarray(points_world, np.float64) - T[:3, 3]) @ T[:3, 2]
