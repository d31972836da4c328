"""Which observed vertices make the map: those seen by enough views, less the teeth of the views' reach.

Each keyframe sees a cone of the road (its field of view, cut at its reach); the union of cones 1 m apart has one
tooth per keyframe along its edge, whose vertices one or two views saw at their reach's limit and at a grazing
angle. The mapped area is opened (eroded, then dilated) by a disc: what a disc of `opening_m` radius cannot reach
from inside the area (teeth and slivers narrower than the disc) is left out, and the edge follows the smooth
envelope of the cones instead of each cone. Straight and gently curving edges, and the corridor's, stay where they
are; convex corners are rounded to the disc.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt

from mapping.method.road_mesh import RoadMesh


def mapped_vertices(mesh: RoadMesh, views: np.ndarray, min_views: int, opening_m: float) -> np.ndarray:
    """(N,) bool: the vertices seen by at least `min_views` views (`views`: (N,) counts) that a disc of radius
    `opening_m` inside that area reaches (opening_m <= 0: no opening). The opening is on the mesh's lattice
    (rows `row_spacing_m`, columns `side_m` apart; the odd rows' half-column shift is below the disc's scale)."""
    seen = views >= max(min_views, 1)
    if opening_m <= 0 or not seen.any():
        return seen
    rc = mesh.rc[seen]
    pad = int(np.ceil(opening_m / mesh.row_spacing_m)) + 2
    low = rc.min(0) - pad
    shape = tuple(rc.max(0) - low + pad + 1)
    area = np.zeros(shape, bool)
    area[rc[:, 0] - low[0], rc[:, 1] - low[1]] = True
    spacing = (mesh.row_spacing_m, mesh.side_m)
    core = distance_transform_edt(area, sampling=spacing) > opening_m  # the disc's centres that fit inside
    if not core.any():
        return np.zeros_like(seen)
    reached = distance_transform_edt(~core, sampling=spacing) <= opening_m
    keep = seen.copy()
    keep[seen] = reached[rc[:, 0] - low[0], rc[:, 1] - low[1]]
    return keep
