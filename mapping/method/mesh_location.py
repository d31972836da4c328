"""Points placed on the road mesh ahead of time (`Located`): the triangle under each point and its barycentric
weights, from the mesh's x, y only, so before any fit; the supervision (Lidar targets, Lidar detail) and the
metrics read the map through them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapping.method.road_map import RoadMap
from mapping.method.road_mesh import RoadMesh, locate

LOCATE_CHUNK = 1 << 16  # points located at once ahead of time


def all_observed(road_map: RoadMap, ids: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(M,) whether the three vertices of each valid triangle `ids` (M, 3) were supervised."""
    seen = road_map.observed[np.where(ok[:, None], ids, 0)] > 0
    return seen[:, 0] & seen[:, 1] & seen[:, 2]


@dataclass(frozen=True)
class Located:
    """Points placed on the mesh (its x, y only, so before the fit): the triangle under each (vertex ids),
    the barycentric weights, and whether it lies inside the mesh."""

    ids: np.ndarray  # (M, 3) int32
    weights: np.ndarray  # (M, 3) float32
    inside: np.ndarray  # (M,) bool

    @staticmethod
    def of(mesh: RoadMesh, xy: np.ndarray) -> Located:
        """In chunks: this runs beside other threads' work (the image decoding, the other set of points), and
        numpy's fancy indexing holds the GIL for as long as it runs (whole-array calls slowed the fit beside
        them)."""
        ids, w, ok = np.empty((len(xy), 3), np.int32), np.empty((len(xy), 3), np.float32), np.empty(len(xy), bool)
        for lo in range(0, len(xy), LOCATE_CHUNK):
            part = slice(lo, lo + LOCATE_CHUNK)
            ids[part], w[part], ok[part] = locate(mesh, xy[part])
        return Located(ids, w, ok)

    def observed(self, road_map: RoadMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As mapping.outputs.map_metrics.observed_triangles: inside and all three vertices supervised."""
        return self.ids, self.weights, self.inside & all_observed(road_map, self.ids, self.inside)
