"""What the keyframes saw at each mesh vertex: every vertex within reach of a keyframe is projected into
it (pinhole + distortion) and reads the image's colour (bilinear) and the mask's label (nearest pixel).

This is the fast path's rendering run backwards: instead of asking which triangle each pixel sees, each
vertex asks which pixel sees it. Per vertex it accumulates a label histogram (the semantic
cross-entropy summed over a vertex's observations is minimised by the log of its label frequencies),
read over the vertex's footprint when the mesh's neighbours are given: its hat function sampled on a lattice
that splits each edge in parts (`fast_fit.label_footprint_subdivision`, 4 by default: the vertex, three points
along each edge, three inside each triangle, each label to the triangle's corners by its barycentric weights),
as the paper's per-pixel loss spreads a pixel's label over the three vertices of the triangle it sees (a
boundary then falls between vertices where the labels change, not on the nearest vertex; the half-edge
lattice, 5 cm between reads, aliased a 12-16 cm stripe's share). A view's labels count less where its pixel
covers more ground along the line of sight than `label_sharp_m` (a camera 1.5 m up with f = 1000 px covers 1.7
cm at 5 m, 15 cm at 15 m): far, grazing views smear a lane marking's edge over many vertices, near ones place
it. Per camera it also accumulates the sum and count of the colours each vertex was seen with (the targets the
colour codes and the camera decoders are fitted to). Pixels the mask marks as obstacles or unlabelled are not
used, so cars never reach the map (a keyframe without a mask gives every vertex in view its colour and no
label, less those the Lidar's occlusion test finds hidden: mapping.fits.lidar_occlusion). Every pixel near the
vertex counts through the bilinear read; each vertex is seen from many keyframes at different sub-pixel
positions, which averages out image noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from daemon.spine.semantic_classes import NUM_MAP_CLASSES
from mapping.fits.colour_consensus import ColourReads, consensus, proximity_weight
from mapping.method.mesh_renderer import max_r2, to_camera
from mapping.method.scene_data import CameraModel, Keyframe

if TYPE_CHECKING:  # the test projects with this module's project_points
    from mapping.fits.lidar_occlusion import OcclusionTest

NEAR_M = 0.5


@dataclass
class VertexObservations:
    """Accumulated observations of every mesh vertex (rows = vertex ids)."""

    camera_names: list[str]
    label_counts: np.ndarray  # (N, NUM_MAP_CLASSES) float32
    colour_sum: np.ndarray  # (N, n_cameras, 3) float32, RGB in [0, 1]
    colour_count: np.ndarray  # (N, n_cameras) float32
    maskless_reads: int = 0  # colour reads of the views without semantics, before the occlusion test
    maskless_hidden: int = 0  # of them, left out as hidden by what the Lidar saw standing on the road
    maskless_unchecked: int = 0  # views without semantics with no Lidar scan near enough in time to test
    consensus_reads: ColourReads | None = None  # those views' colour reads kept for their consensus
    # (mapping.fits.colour_consensus) instead of summed; None: summed as a mask's road pixels are
    consensus_rejected: int = 0  # of the reads kept, those that disagreed with their vertex's consensus

    @staticmethod
    def empty(num_vertices: int, camera_names: list[str], consensus: bool = False) -> VertexObservations:
        c = len(camera_names)
        return VertexObservations(list(camera_names), np.zeros((num_vertices, NUM_MAP_CLASSES), np.float32),
                                  np.zeros((num_vertices, c, 3), np.float32), np.zeros((num_vertices, c), np.float32),
                                  consensus_reads=ColourReads() if consensus else None)

    @property
    def seen(self) -> np.ndarray:
        """Vertex ids with at least one colour observation."""
        return np.nonzero(self.colour_count.sum(1) > 0)[0]

    def add(self, other: VertexObservations) -> None:
        """Add another set of observations of the same vertices and cameras to these."""
        if other.camera_names != self.camera_names or other.label_counts.shape != self.label_counts.shape:
            raise ValueError("observations of different meshes or cameras")
        self.label_counts += other.label_counts
        self.colour_sum += other.colour_sum
        self.colour_count += other.colour_count
        self.maskless_reads += other.maskless_reads
        self.maskless_hidden += other.maskless_hidden
        self.maskless_unchecked += other.maskless_unchecked
        if other.consensus_reads is not None:
            if self.consensus_reads is None:
                self.consensus_reads = ColourReads()
            self.consensus_reads.extend(other.consensus_reads)

    def fold_consensus(self, tolerance: float) -> None:
        """The kept reads' consensus colours (mapping.fits.colour_consensus) into the colour sums, each weighing as
        many views as agreed with it."""
        reads, self.consensus_reads = self.consensus_reads, None
        if reads is None or not len(reads):
            return
        c = len(self.camera_names)
        agreed = consensus(reads, c, tolerance)
        vertex, camera = agreed.key // c, agreed.key % c
        self.colour_sum[vertex, camera] += agreed.colour * agreed.inliers[:, None]
        self.colour_count[vertex, camera] += agreed.inliers
        self.consensus_rejected += int((agreed.reads - agreed.inliers).sum())

    def colour_mean(self, ids: np.ndarray) -> np.ndarray:
        return self.colour_sum[ids] / np.maximum(self.colour_count[ids], 1.0)[..., None]


def project_points(points_world: np.ndarray, camera: CameraModel, T_world_camera: np.ndarray):
    """Pixel coordinates (M, 2) of world points and which of them are in front and inside the image."""
    return project_camera_points(to_camera(T_world_camera, points_world), camera)


def project_camera_points(p: np.ndarray, camera: CameraModel):
    """Pixel coordinates (M, 2) of camera-frame points (M, 3) and which of them are in front and inside the
    image."""
    z = p[:, 2]
    ok = z > NEAR_M
    zs = np.where(ok, z, 1.0)
    x, y = p[:, 0] / zs, p[:, 1] / zs
    r2 = x * x + y * y
    ok &= r2 <= max_r2(camera)
    if camera.distorted:
        k1, k2, p1, p2, k3 = camera.distortion
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
    (fx, skew, cx), (_, fy, cy) = camera.K[:2].tolist()
    u, v = fx * x + skew * y + cx, fy * y + cy
    ok &= (u >= 0) & (u <= camera.width - 1) & (v >= 0) & (v <= camera.height - 1)
    return np.stack([u, v], 1), ok


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(M, C) float32 image values at (M, 2) pixel coordinates inside the image."""
    h, w = image.shape[:2]
    u0 = np.minimum(np.floor(uv[:, 0]).astype(np.int64), w - 2)
    v0 = np.minimum(np.floor(uv[:, 1]).astype(np.int64), h - 2)
    fu = (uv[:, 0] - u0).astype(np.float32)[:, None]
    fv = (uv[:, 1] - v0).astype(np.float32)[:, None]
    flat = image.reshape(h * w, -1)
    i = v0 * w + u0
    top = flat[i] * (1 - fu) + flat[i + 1] * fu
    bottom = flat[i + w] * (1 - fu) + flat[i + w + 1] * fu
    return top * (1 - fv) + bottom * fv


EDGE_DIRECTIONS = (1, 4, 5)  # RoadMesh.neighbours columns that name every undirected edge once
FACE_DIRECTIONS = ((1, 5), (5, 4))  # neighbour column pairs that, with the vertex, name every triangle once
FACE_EDGES = (((1, 0), (5, 0), (4, 1)), ((5, 0), (4, 0), (1, 2)))  # per FACE_DIRECTIONS entry, its triangles' edges
# as (EDGE_DIRECTIONS entry, the corner (0: the vertex, 1, 2: the columns' neighbours) the edge runs from)


@dataclass
class MeshFootprint:
    """What reading labels over the vertices' footprints needs: for each edge direction the neighbour of
    every vertex (-1: none), the lattice's subdivision and, for one thread, a scratch array giving each
    vertex's slot in the keyframe being observed."""

    edge_ends: list[np.ndarray]  # per EDGE_DIRECTIONS entry, (N,) int32 contiguous
    slot: np.ndarray  # (N,) int64 scratch
    subdivision: int  # the lattice splits each triangle's edges into this many parts (2: half edges)

    @staticmethod
    def of(neighbours: np.ndarray, subdivision: int) -> MeshFootprint:
        if subdivision < 1:
            raise ValueError(f"footprint subdivision must be at least 1, got {subdivision}")
        return MeshFootprint([np.ascontiguousarray(neighbours[:, d]) for d in EDGE_DIRECTIONS],
                             np.zeros(len(neighbours), np.int64), subdivision)

    def edge_points(self) -> list[tuple[float, float]]:
        """Barycentric coordinates (to its first and second end) of the lattice points inside an edge."""
        n = self.subdivision
        return [((n - k) / n, k / n) for k in range(1, n)]

    def face_points(self) -> list[tuple[float, float, float]]:
        """Barycentric coordinates of the lattice points strictly inside a triangle."""
        n = self.subdivision
        return [(a / n, b / n, (n - a - b) / n) for a in range(1, n) for b in range(1, n - a)]

    @property
    def scale(self) -> float:
        """A lattice point's weight per unit of hat value: every vertex's footprint then weighs 4 per view, as the
        half-edge lattice's (subdivision 2) does, whatever the subdivision."""
        return 4.0 / self.subdivision ** 2


def label_at(keyframe: Keyframe, uv: np.ndarray) -> np.ndarray:
    """(M,) the keyframe's mask labels at the pixels nearest `uv`."""
    h, w = keyframe.semantics.shape
    pixel = np.rint(uv[:, 1]).astype(np.int64) * w + np.rint(uv[:, 0]).astype(np.int64)
    return keyframe.semantics.reshape(-1)[pixel]


def pixel_ground_length_m(points_world: np.ndarray, camera: CameraModel, T_world_camera: np.ndarray) -> np.ndarray:
    """(N,) length of ground along the line of sight that one pixel covers at each point: z^2 / (f h) for a
    point at depth z (along the optical axis) and h below the camera, for level ground (the pixel spans
    z / f across the ray, which meets the ground at a grazing angle of about h / z); h is floored at 5 cm."""
    delta = points_world - T_world_camera[:3, 3]
    depth = delta @ T_world_camera[:3, 2]
    return depth * depth / (camera.K[1, 1] * np.maximum(-delta[:, 2], 0.05))


def label_weights(points_world: np.ndarray, camera: CameraModel, T_world_camera: np.ndarray,
                  sharp_m: float | None) -> np.ndarray:
    """(N,) float32 weight of the labels a view reads at each point: 1 where its pixel covers at most
    `sharp_m` of ground along the line of sight, sharp_m / length beyond (a far, grazing view places a
    boundary less precisely); all 1 if sharp_m is None."""
    if sharp_m is None:
        return np.ones(len(points_world), np.float32)
    length = pixel_ground_length_m(points_world, camera, T_world_camera)
    return np.minimum(1.0, sharp_m / length).astype(np.float32)


def _label_footprints(obs: VertexObservations, seen: np.ndarray, uv: np.ndarray, centre: np.ndarray,
                      weight: np.ndarray, keyframe: Keyframe, footprint: MeshFootprint) -> np.ndarray:
    """Labels at the footprint lattice's points along every edge whose two ends the keyframe sees and inside
    every triangle whose three corners it sees (`seen`, at pixels `uv`, labels `centre` there, label weights
    `weight`), each to the corners by their hat values (barycentric coordinates), the first corner's label
    weight for all. Over 10 cm the projection is affine to well under a pixel, so a point projects where its
    barycentric coordinates put it between the corners' pixels.

    The points are read only where the labels change: an edge whose ends and middle read one label, and a
    triangle whose corners and edges' middles do, count as that label throughout (a stripe narrower than half an
    edge could hide in one; one as wide as a triangle's height cannot cross it without touching a corner). Their
    weight is returned, per slot of `seen`, for the caller to add to the vertex's own label."""
    slot = footprint.slot
    slot[seen] = np.arange(len(seen))
    classes = obs.label_counts.shape[1]
    uniform_weight = np.zeros(len(seen))
    keys: list[np.ndarray] = []  # vertex * classes + label of every (lattice point read, corner)
    values: list[np.ndarray] = []

    def seen_slots(ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The slots whose neighbour `ends` the keyframe sees, and that neighbour's slots."""
        j = ends[seen]
        k = slot[j]  # j = -1 reads the last vertex's slot: rejected below as it is not -1
        k = np.where(k < len(seen), k, 0)
        both = np.flatnonzero(seen[k] == j)
        return both, k[both]

    def read(corners: list[np.ndarray], uniform: np.ndarray, points: list[tuple[float, ...]]) -> None:
        """The simplices (edges or triangles) with these corner slots: the uniform ones as their corners' label
        throughout, the others read at each of `points` (barycentric coordinates)."""
        if not points:
            return
        w = footprint.scale * weight[corners[0]]
        uniform_w = w * uniform
        for hat, c in zip(np.sum(points, 0), corners, strict=True):
            uniform_weight[:] += np.bincount(c, hat * uniform_w, len(seen))
        mixed = np.flatnonzero(~uniform)
        corners, w = [c[mixed] for c in corners], w[mixed]
        corner_uv, corner_key = [uv[c] for c in corners], [seen[c] * classes for c in corners]
        for bary in points:
            label = label_at(keyframe, sum(b * p for b, p in zip(bary, corner_uv, strict=True)))
            good = np.flatnonzero(label < NUM_MAP_CLASSES)
            for b, key in zip(bary, corner_key, strict=True):
                keys.append(key[good] + label[good])
                values.append(b * w[good])

    edge_points, interior = footprint.edge_points(), footprint.face_points()
    other_end, middle = {}, {}  # for the triangles, per edge direction, (len(seen),) each slot's neighbour's slot
    for direction, ends in zip(EDGE_DIRECTIONS, footprint.edge_ends, strict=True):  # (-1: not seen) and the label
        first, second = seen_slots(ends)  # half-way there
        half = label_at(keyframe, 0.5 * (uv[first] + uv[second]))
        if interior:
            other_end[direction] = np.full(len(seen), -1, np.int64)
            other_end[direction][first] = second
            middle[direction] = np.full(len(seen), 255, np.uint8)
            middle[direction][first] = half
        read([first, second], (centre[first] == half) & (centre[second] == half), edge_points)
    for (db, dc), edges in zip(FACE_DIRECTIONS, FACE_EDGES, strict=True) if interior else ():
        a = np.flatnonzero((other_end[db] >= 0) & (other_end[dc] >= 0))
        corners = [a, other_end[db][a], other_end[dc][a]]
        label = centre[a]
        uniform = (centre[corners[1]] == label) & (centre[corners[2]] == label)
        for direction, base in edges:
            uniform &= middle[direction][corners[base]] == label
        read(corners, uniform, interior)
    if keys:
        np.add.at(obs.label_counts.reshape(-1), np.concatenate(keys), np.concatenate(values).astype(np.float32))
    return uniform_weight


def observe_keyframe(obs: VertexObservations, ids: np.ndarray, points_world: np.ndarray, keyframe: Keyframe,
                     camera: CameraModel, footprint: MeshFootprint | None = None,
                     label_sharp_m: float | None = None, occlusion: OcclusionTest | None = None,
                     consensus_near_m: float = 5.0) -> int:
    """Add one keyframe's view of the vertices `ids` (unique; world positions `points_world`), the labels
    over their footprints if `footprint` is given, weighted by label_weights(..., label_sharp_m); returns how
    many vertices it labelled at their centre. A keyframe without semantics adds the colours of every vertex
    in view that `occlusion` (if given) does not find hidden, and no labels: into the sums, or into
    `obs.consensus_reads` (if kept) weighted by proximity_weight(distance, consensus_near_m)."""
    uv, ok = project_points(points_world, camera, keyframe.T_world_camera)
    ids, uv, points = ids[ok], uv[ok], points_world[ok]
    if keyframe.semantics is None:  # no mask: no labels, and every vertex in view not hidden reads its colour
        obs.maskless_reads += len(ids)
        hidden = occlusion.hidden(keyframe, camera, uv, points) if occlusion is not None else None
        if hidden is not None:
            obs.maskless_hidden += int(hidden.sum())
            ids, uv, points = ids[~hidden], uv[~hidden], points[~hidden]
        elif occlusion is not None:
            obs.maskless_unchecked += 1
        if obs.consensus_reads is None:
            _add_colours(obs, ids, uv, keyframe, camera)
            return 0
        distance = np.linalg.norm(points - keyframe.T_world_camera[:3, 3], axis=1)
        obs.consensus_reads.append(ids, obs.camera_names.index(camera.name), bilinear(keyframe.image, uv) / 255.0,
                                   proximity_weight(distance, consensus_near_m))
        return 0
    weight = label_weights(points, camera, keyframe.T_world_camera, label_sharp_m)
    label = label_at(keyframe, uv)
    if footprint is not None:
        weight = weight * footprint.scale + _label_footprints(obs, ids, uv, label, weight, keyframe, footprint)
    good = label < NUM_MAP_CLASSES
    ids, uv, label, weight = ids[good], uv[good], label[good].astype(np.int64), weight[good]
    if len(ids) == 0:
        return 0
    obs.label_counts.reshape(-1)[ids * obs.label_counts.shape[1] + label] += weight  # ids are unique in a keyframe
    _add_colours(obs, ids, uv, keyframe, camera)
    return len(ids)


def _add_colours(obs: VertexObservations, ids: np.ndarray, uv: np.ndarray, keyframe: Keyframe,
                 camera: CameraModel) -> None:
    """The colours the keyframe shows at pixels `uv` of the vertices `ids` (unique) into their camera's sums."""
    c = obs.camera_names.index(camera.name)
    obs.colour_sum[ids, c] += bilinear(keyframe.image, uv) / 255.0
    obs.colour_count[ids, c] += 1.0
