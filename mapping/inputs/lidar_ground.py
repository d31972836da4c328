"""Lidar ground points for the elevation loss: scans -> world points -> ground points only (and, for views
without masks, the points standing on the road: standing_points).

A scan comes as raw Ouster packets, as another vendor's raw packets (Velodyne, Hesai, RoboSense: a scan is the
packets stamped within one rotation period), or as a decoded PointCloud (any vendor's, `lidar/points`); decoding it
into ScanPoints (points in the Lidar frame, each with its firing time) is the only step that differs. Points are then
moved into the world frame with the vehicle pose at their time (motion compensated). The ground filter keeps
points within a height band around the trajectory's ground height under them, then, on a 0.5 m grid, only points
close to the lowest point of their cell or on a flat patch at most a curb's height above it: points on cars and
other things standing on the road are dropped. The trajectory's ground height is rasterised once per drive
(TrajectoryGround): each `ground_cell_m` cell within the corridor holds the height of the trajectory point nearest
to the cell's centre, so that the filter looks each point up in its cell instead of searching for its nearest
trajectory point (a k-d tree query per point was a large part of loading a drive); past the trajectory's first and
last points it follows their grade (a 4 % grade drops 48 cm over the 12 m a front camera maps beyond the end of a
drive, more than the band: that road's points were all dropped and its labels placed on an extrapolated surface).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from daemon.spine.config import CarConfig, LidarConfig
from daemon.spine.messages import LidarPacket, PointCloud
from daemon.spine.point_cloud_codec import point_array
from daemon.spine.topics import LIDAR_PACKETS, LIDAR_POINTS, LIDAR_VIEW
from drivers.lidar.lidar_models import configured_decoder
from drivers.lidar.lidar_points import XYZLut, batch_xyz
from drivers.lidar.ouster_decoder import decode_packets
from drivers.lidar.ouster_metadata import OusterMetadata, configured_metadata
from drivers.lidar.ouster_packet_layout import OusterPacketLayout, packet_layout
from drivers.lidar.ouster_xyz import make_xyz_lut
from drivers.lidar.packet_decoding import PacketDecoder
from mapping.inputs.static_ground import StaticGround, static_index
from mapping.localization.sensor_time import ClockMap
from mapping.localization.trajectory import Trajectory
from mapping.method.scene_data import StandingPoints

TILE_CELLS = 64  # the ground raster is stored as square tiles of this many cells a side, only near the trajectory
TILES_PER_QUERY = 256  # tiles whose cell centres are looked up in the trajectory k-d tree at once
STANDING_VOXEL_M = 0.2  # standing points are thinned to one per voxel: ~2,600 a scan on the city drive
END_GRADE_M = 5.0  # beyond the trajectory's ends the road's height follows the grade of its last metres


def keeps_scan(packet_index: int, packets_per_scan: int, every_n_scans: int) -> bool:
    """Whether the Lidar scan holding the `packet_index`-th packet (counted from the first, `packets_per_scan`
    to a scan; a PointCloud is a scan of one) is used: every n-th scan (`mapper.inputs.lidar_every_n_scans`), the
    first one included."""
    return (packet_index // packets_per_scan) % every_n_scans == 0


@dataclass(frozen=True)
class GroundFilter:
    max_range_m: float = 40.0
    min_range_m: float = 2.0
    band_m: float = 0.35  # kept when within this of the trajectory ground height
    corridor_half_width_m: float = 15.0
    cell_m: float = 0.5
    above_cell_min_m: float = 0.08  # kept when within this of the lowest point of its grid cell ...
    # ... or when on a flat raised patch: a quarter of the grid cell whose points (at least `flat_min_points`)
    # lie within `flat_span_m` of each other, at most `raised_max_m` above the lowest point of the grid cell. A
    # grid cell straddling a curb otherwise drops the curb top (15 cm above the gutter), which the Lidar detail
    # needs; a car's side spans its whole height in any cell and is still dropped.
    flat_span_m: float = 0.04
    flat_min_points: int = 4
    raised_max_m: float = 0.2
    voxel_m: float = 0.1  # at most one point per voxel of this size (per scan)
    static: StaticGround | None = StaticGround()  # then only the points the scans agree on
    # (mapping.inputs.static_ground: a passing car's lowest points are dropped); None: every scan's on its own
    ground_cell_m: float = 0.25  # cell of the trajectory ground raster (TrajectoryGround)


def scan_number(decoding: OusterMetadata | VendorDecoding | None, topic: str, count: int, message: object) -> int:
    """The scan of a drive's `count`-th Lidar message (counted from the first) on `topic`, as keeps_scan numbers
    them: an Ouster's packets `packets_per_frame` to a scan, a vendor Lidar's by the rotation period their stamps
    fall in, a PointCloud one scan each."""
    if topic == LIDAR_POINTS or decoding is None:
        return count
    if isinstance(decoding, VendorDecoding):
        return message.sensor_time_ns // decoding.rotation_period_ns
    return count // decoding.packets_per_frame


@dataclass(frozen=True)
class LidarDecoding:
    """What decoding one sensor's packets needs, built once per drive."""

    layout: OusterPacketLayout
    lut: XYZLut

    @staticmethod
    def of(metadata: OusterMetadata) -> LidarDecoding:
        return LidarDecoding(packet_layout(metadata), make_xyz_lut(metadata))


@dataclass(frozen=True)
class ScanPoints:
    """One scan's points in the Lidar frame, whatever they were decoded from: point k fired at sensor time
    times_ns[time_index[k]] (the points of one Ouster column share their column's time)."""

    xyz: np.ndarray  # (N, 3) float32 metres, Lidar frame (x forward, y left, z up); no return: (0, 0, 0)
    time_index: np.ndarray  # (N,) int64 into times_ns
    times_ns: np.ndarray  # (T,) int64, sensor clock
    intensity: np.ndarray | None = None  # (N,) as the sensor reports it (Ouster: signal, else reflectivity)


def packet_scan_points(packets: list[bytes], decoding: LidarDecoding) -> ScanPoints:
    """An Ouster scan's packets decoded: every pixel of the valid columns, in packet, column, beam order."""
    batch = decode_packets(packets, decoding.layout)
    if batch.num_packets == 0:
        return ScanPoints(np.zeros((0, 3), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64))
    valid = batch.column_valid.ravel()
    xyz = batch_xyz(batch, decoding.lut).reshape(len(valid), -1, 3)  # (P * K, H, 3)
    if not valid.all():
        xyz = xyz[valid]
    times = batch.timestamp_ns.ravel()[valid].astype(np.int64)
    strength = (batch.signal if batch.signal is not None else batch.reflectivity).reshape(len(valid), -1)[valid]
    return ScanPoints(xyz.reshape(-1, 3), np.repeat(np.arange(len(times)), xyz.shape[1]), times,
                      strength.ravel().astype(np.float32))


@dataclass(frozen=True)
class VendorDecoding:
    """How a vendor Lidar's packets decode: a fresh decoder per scan (decoders keep state from packet to packet,
    and scans are decoded on several threads), and the rotation period that groups packets into scans."""

    new_decoder: Callable[[], PacketDecoder]
    rotation_period_ns: int


def configured_decoding(lidar: LidarConfig, config_path: str | Path) -> OusterMetadata | VendorDecoding | None:
    """How the configured Lidar's packets decode (None: a point-cloud Lidar, it has none); a calibration or
    metadata file that cannot be read or does not fit the model is a ConfigError naming it."""
    if lidar.point_clouds:
        return None
    if not lidar.vendor_packets:
        return configured_metadata(lidar, config_path)
    prototype = configured_decoder(lidar, config_path)
    return VendorDecoding(lambda: copy.deepcopy(prototype), round(1e9 / lidar.rate_hz))


def vendor_scan_points(lead: LidarPacket | None, packets: list[LidarPacket], decoding: VendorDecoding) -> ScanPoints:
    """A vendor scan's packets decoded, each point at its packet's message stamp plus its firing offset within the
    packet (the packet's own stamp may count past the hour: Velodyne). The `lead` packet (the one before the scan)
    only primes the decoder (a VLS-128 takes its rotation rate from the packet before) and gives no points."""
    payloads = ([bytes(lead.data)] if lead is not None else []) + [bytes(p.data) for p in packets]
    stamps = np.array(([lead.sensor_time_ns] if lead is not None else []) + [p.sensor_time_ns for p in packets],
                      dtype=np.int64)
    points = decoding.new_decoder().decode(payloads)
    keep = np.flatnonzero(points.packet_index >= (1 if lead is not None else 0))
    packet = points.packet_index[keep]
    times_ns = stamps[packet] + (points.timestamp_ns[keep] - points.packet_time_ns[packet])
    times, time_index = np.unique(times_ns, return_inverse=True)
    return ScanPoints(points.xyz[keep], time_index.ravel(), times, points.intensity[keep])


def vendor_packet_scans(packets: list[LidarPacket], decoding: VendorDecoding, every_n_scans: int) -> LidarScans:
    """Every n-th scan of a vendor Lidar's packets (a scan: consecutive packets stamped within the same rotation
    period, counted from the first scan), each with the packet before it as its lead."""
    if not packets:
        return LidarScans(LIDAR_PACKETS, [], lambda scan: vendor_scan_points(*scan, decoding), 0)
    period = np.array([p.sensor_time_ns for p in packets], dtype=np.int64) // decoding.rotation_period_ns
    starts = np.concatenate([[0], np.flatnonzero(np.diff(period) != 0) + 1, [len(packets)]])
    scans = [(packets[a - 1] if a > 0 else None, packets[a:b]) for k, (a, b) in enumerate(zip(starts[:-1],
             starts[1:], strict=True)) if keeps_scan(k, 1, every_n_scans)]
    return LidarScans(LIDAR_PACKETS, scans, lambda scan: vendor_scan_points(*scan, decoding), len(packets))


def scan_decoder(decoding: OusterMetadata | VendorDecoding) -> Callable[[LidarPacket | None, list[LidarPacket]],
                                                                         ScanPoints]:
    """How one scan's packets (and the packet before them, which a vendor decoder is primed with) become ScanPoints,
    for any Lidar that sends packets: one scan at a time, as a live consumer gets them (the viewing clouds)."""
    if isinstance(decoding, VendorDecoding):
        return lambda lead, packets: vendor_scan_points(lead, packets, decoding)
    ouster = LidarDecoding.of(decoding)
    return lambda _lead, packets: packet_scan_points([bytes(p.data) for p in packets], ouster)


def cloud_scan_points(cloud: PointCloud) -> ScanPoints:
    """A decoded scan's points, in the cloud's order, each at its own time (to the nanosecond)."""
    points = point_array(cloud)
    offsets_ns = np.rint(points[:, 4].astype(np.float64) * 1e9).astype(np.int64)
    offsets, time_index = np.unique(offsets_ns, return_inverse=True)
    return ScanPoints(points[:, :3], time_index.ravel(), int(cloud.sensor_time_ns) + offsets, points[:, 3])


def lidar_world_points(scan: ScanPoints, clock: ClockMap, T_vehicle_lidar: np.ndarray, trajectory: Trajectory,
                       settings: GroundFilter) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (N, 3) of one scan, motion compensated, in the scan's order: those in the range band (distance
    from the Lidar frame's origin) fired within the trajectory's time span, each moved with the pose at its time
    composed with the Lidar mounting (T_world_vehicle(t) @ T_vehicle_lidar); each point's firing time (N,)
    in seconds from the trajectory's start; and which of the scan's points they are (N,) (increasing)."""
    times = clock.to_host(scan.times_ns)
    inside = (times >= trajectory.times_ns[0]) & (times <= trajectory.times_ns[-1])
    rng = np.linalg.norm(scan.xyz, axis=1)
    flat = np.flatnonzero((rng > settings.min_range_m) & (rng < settings.max_range_m) & inside[scan.time_index])
    if not len(flat):
        return np.zeros((0, 3)), np.zeros(0), flat
    used, point_time = np.unique(scan.time_index[flat], return_inverse=True)
    positions, quats = trajectory.interpolate(times[used])
    R_world_vehicle = Rotation.from_quat(quats)
    R = (R_world_vehicle * Rotation.from_matrix(T_vehicle_lidar[:3, :3])).as_matrix()  # (T, 3, 3) world <- Lidar
    t = positions + R_world_vehicle.apply(T_vehicle_lidar[:3, 3])  # (T, 3)
    xyz = scan.xyz[flat].astype(np.float64)  # (N, 3) Lidar frame
    R, t = R[point_time.ravel()], t[point_time.ravel()]
    seconds = (np.asarray(times, np.int64)[scan.time_index[flat]] - int(trajectory.times_ns[0])) / 1e9
    return (R[:, :, 0] * xyz[:, 0:1] + R[:, :, 1] * xyz[:, 1:2] + R[:, :, 2] * xyz[:, 2:3]) + t, seconds, flat


INTENSITY_GROUP = 256  # a ground point's intensity contrast: against the median of this many of its scan's ground
# points nearest to it in range


def intensity_contrast(intensity: np.ndarray | None, distance: np.ndarray) -> np.ndarray:
    """Each ground point's intensity as a contrast to the road around it at its range: log(1 + I) less the median
    of log(1 + I) over the INTENSITY_GROUP points of the scan nearest in range (the road there, mostly asphalt).
    Whatever the sensor reports (an Ouster's signal falls with range, a Velodyne's reflectance less so), paint then
    stands out by about the same amount near and far. NaN without intensities (mapping.fits.lidar_registration
    then uses the heights only)."""
    if intensity is None or len(distance) == 0:
        return np.full(len(distance), np.nan, np.float32)
    order = np.argsort(distance, kind="stable")
    value = np.log1p(np.maximum(np.asarray(intensity, np.float64)[order], 0.0))
    groups = max(1, len(value) // INTENSITY_GROUP)
    bounds = np.linspace(0, len(value), groups + 1).astype(np.int64)
    median = np.concatenate([np.full(b - a, np.median(value[a:b]))
                             for a, b in zip(bounds[:-1], bounds[1:], strict=True)])
    out = np.empty(len(value), np.float32)
    out[order] = value - median
    return out


def _tile_key(tiles: np.ndarray) -> np.ndarray:
    return tiles[..., 0] * (1 << 32) + tiles[..., 1]


@dataclass(frozen=True)
class TrajectoryGround:
    """The road height under the trajectory, rasterised once per drive (see the module docstring).

    Cell (i, j) covers [i, i + 1) x [j, j + 1) times `cell_m` in x and y; tile (a, b) holds cells
    (a * TILE_CELLS + u, b * TILE_CELLS + v). Cells whose centre lies further than the corridor half-width
    from every trajectory point hold NaN; tiles without any cell in the corridor are not stored. A cell whose
    nearest trajectory point is the first or the last holds that point's height plus its grade (end_grade) times
    the cell's distance beyond it."""

    cell_m: float
    tile_keys: np.ndarray  # (T,) sorted int64 keys of the stored tiles (_tile_key)
    heights: np.ndarray  # (T, TILE_CELLS, TILE_CELLS) float32 ground height, NaN outside the corridor

    @staticmethod
    def of(trajectory: Trajectory, reference_height_m: float, corridor_half_width_m: float,
           cell_m: float = 0.25) -> TrajectoryGround:
        ground = trajectory.positions.copy()
        ground[:, 2] -= reference_height_m
        tree = cKDTree(ground[:, :2])
        tile_m = TILE_CELLS * cell_m
        reach = corridor_half_width_m + cell_m
        lo = np.floor((ground[:, :2] - reach) / tile_m).astype(np.int64)
        span = int(np.floor(2 * reach / tile_m)) + 2  # tiles a square of side 2 * reach can touch, per axis
        offsets = np.stack(np.meshgrid(np.arange(span), np.arange(span), indexing="ij"), -1).reshape(-1, 2)
        candidates = (lo[:, None, :] + offsets[None]).reshape(-1, 2)
        keys, first = np.unique(_tile_key(candidates), return_index=True)
        tiles = candidates[first]
        uv = np.stack(np.meshgrid(np.arange(TILE_CELLS), np.arange(TILE_CELLS), indexing="ij"), -1) + 0.5
        heights = np.full((len(tiles), TILE_CELLS, TILE_CELLS), np.nan, np.float32)
        ends = [end_grade(ground, at_start) for at_start in (True, False)]
        for start in range(0, len(tiles), TILES_PER_QUERY):
            part = slice(start, start + TILES_PER_QUERY)
            centres = ((tiles[part, None, None, :] * TILE_CELLS + uv[None]) * cell_m).reshape(-1, 2)
            dist, idx = tree.query(centres, distance_upper_bound=corridor_half_width_m)
            near = np.isfinite(dist)
            z = np.full(len(dist), np.nan, np.float32)
            z[near] = ground[idx[near], 2]
            for at, outward, grade in ends:
                past = near & (idx == at)  # beyond the trajectory's end: the road goes on at the end's grade
                beyond = np.maximum((centres[past] - ground[at, :2]) @ outward, 0.0)
                z[past] = ground[at, 2] + grade * beyond
            heights[part] = z.reshape(-1, TILE_CELLS, TILE_CELLS)
        stored = ~np.isnan(heights).all((1, 2))
        return TrajectoryGround(cell_m, keys[stored], heights[stored])

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """(N,) ground height of the cell under each point; NaN outside the corridor."""
        cell = np.floor(xy / self.cell_m).astype(np.int64)
        tile = cell // TILE_CELLS
        key = _tile_key(tile)
        pos = np.minimum(np.searchsorted(self.tile_keys, key), len(self.tile_keys) - 1)
        found = self.tile_keys[pos] == key
        within = cell - tile * TILE_CELLS
        out = self.heights[pos, within[:, 0], within[:, 1]]
        out[~found] = np.nan
        return out


def end_grade(ground: np.ndarray, first: bool) -> tuple[int, np.ndarray, float]:
    """At the first (or last) point of a trajectory's ground `ground` (N, 3): its index, the unit horizontal
    direction out of the trajectory there and the road's grade along it (rise over run; 0 when the ends' last
    END_GRADE_M are travelled less than a metre), over the last END_GRADE_M of horizontal travel."""
    step = np.linalg.norm(np.diff(ground[:, :2], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(step)])
    if first:
        at, other = 0, int(np.searchsorted(travelled, END_GRADE_M))
    else:
        at, other = len(ground) - 1, int(np.searchsorted(travelled, travelled[-1] - END_GRADE_M, side="right")) - 1
    other = min(max(other, 0), len(ground) - 1)
    chord = ground[at, :2] - ground[other, :2]
    run = float(np.linalg.norm(chord))
    if run < 1.0:
        return at, np.zeros(2), 0.0
    return at, chord / run, float(ground[at, 2] - ground[other, 2]) / run


def _cell_key(cells: np.ndarray) -> np.ndarray:
    """One int64 key per row of an int64 cell array, equal for equal rows and ordered as the rows."""
    key = np.zeros(len(cells), np.int64)
    for k in range(cells.shape[1]):
        key = key * 2_000_003 + (cells[:, k] + 1_000_001)
    return key


def _first_per_cell(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first index, inverse) of the distinct rows of an int64 cell array, through one int64 key per row."""
    _, first, inverse = np.unique(_cell_key(cells), return_index=True, return_inverse=True)
    return first, inverse.ravel()


def _on_ground(pts: np.ndarray, settings: GroundFilter) -> np.ndarray:
    """Which points are close to their grid cell's lowest point or on a flat raised quarter of the cell.
    One sort serves both: the key orders points by grid cell, then by quarter within it."""
    quarter = np.floor(pts[:, :2] / (0.5 * settings.cell_m)).astype(np.int64)
    cell = quarter >> 1
    key = _cell_key(cell) * 4 + (quarter[:, 0] & 1) * 2 + (quarter[:, 1] & 1)
    order = np.argsort(key, kind="stable")
    key, z = key[order], pts[order, 2]

    def runs(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # start of each run of equal keys, run of each
        starts = np.flatnonzero(np.concatenate([[True], k[1:] != k[:-1]]))
        return starts, np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(k))))

    cell_starts, cell_of = runs(key >> 2)
    low = np.minimum.reduceat(z, cell_starts)[cell_of]
    q_starts, q_of = runs(key)
    q_low, q_high = np.minimum.reduceat(z, q_starts), np.maximum.reduceat(z, q_starts)
    q_count = np.diff(np.append(q_starts, len(z)))
    flat = (q_high - q_low < settings.flat_span_m) & (q_count >= settings.flat_min_points)
    raised = flat[q_of] & (q_low[q_of] - low < settings.raised_max_m)
    keep = np.empty(len(z), bool)
    keep[order] = (z - low < settings.above_cell_min_m) | raised
    return keep


def ground_points(world: np.ndarray, road: TrajectoryGround, settings: GroundFilter) -> np.ndarray:
    """The points of `world` that lie on the road surface (see the module docstring)."""
    return world[ground_index(world, road, settings)]


def ground_index(world: np.ndarray, road: TrajectoryGround, settings: GroundFilter) -> np.ndarray:
    """Which points of `world` (increasing indices) lie on the road surface (see the module docstring)."""
    with np.errstate(invalid="ignore"):  # NaN: outside the corridor, not kept
        near = np.flatnonzero(np.abs(world[:, 2] - road.height_at(world[:, :2])) < settings.band_m)
    if len(near) == 0:
        return near
    near = near[_on_ground(world[near], settings)]
    first, _ = _first_per_cell(np.floor(world[near] / settings.voxel_m).astype(np.int64))
    return near[np.sort(first)]


def standing_points(world: np.ndarray, road: TrajectoryGround, min_m: float, max_m: float,
                    voxel_m: float = STANDING_VOXEL_M) -> np.ndarray:
    """(M, 3) float32 points of `world` standing on the road: between `min_m` and `max_m` above the trajectory's
    ground under them, inside the corridor (cars, people, walls; what hides the road from a camera), at most
    one per `voxel_m` voxel (the first)."""
    if len(world) == 0:
        return np.zeros((0, 3), np.float32)
    with np.errstate(invalid="ignore"):  # NaN: outside the corridor, not kept
        height = world[:, 2] - road.height_at(world[:, :2])
        pts = world[(height > min_m) & (height < max_m)]
    first, _ = _first_per_cell(np.floor(pts / voxel_m).astype(np.int64))
    return pts[np.sort(first)].astype(np.float32)


@dataclass(frozen=True)
class LidarScans:
    """The Lidar scans of a drive or a window as the log holds them, and how each becomes ScanPoints: per scan
    the list of its packets (packet_scan_points), or one PointCloud (cloud_scan_points)."""

    topic: str  # whose clock their stamps are on
    scans: list
    decode: Callable[[object], ScanPoints]
    messages: int  # messages they came in (packets or point clouds)

    @property
    def counts(self) -> dict[str, int]:
        """Those messages as the drive's input counts and the worker's journal name them."""
        name = {LIDAR_POINTS: "lidar_point_clouds", LIDAR_VIEW: "lidar_view_clouds"}.get(self.topic, "lidar_packets")
        return {name: self.messages}


def packet_scans(packets: list[LidarPacket], metadata: OusterMetadata, every_n_scans: int) -> LidarScans:
    """Every n-th scan of an Ouster's packets (a scan: `packets_per_frame` packets, counted from the first)."""
    per_scan, decoding = metadata.packets_per_frame, LidarDecoding.of(metadata)
    chunks = [packets[start:start + per_scan] for start in range(0, len(packets), per_scan)
              if keeps_scan(start, per_scan, every_n_scans)]
    return LidarScans(LIDAR_PACKETS, chunks, lambda chunk: packet_scan_points([bytes(p.data) for p in chunk],
                                                                                decoding), len(packets))


def point_cloud_scans(clouds: list[PointCloud], every_n_scans: int, topic: str = LIDAR_POINTS) -> LidarScans:
    """Every n-th of a Lidar's decoded scans."""
    kept = [cloud for k, cloud in enumerate(clouds) if keeps_scan(k, 1, every_n_scans)]
    return LidarScans(topic, kept, cloud_scan_points, len(clouds))


def lidar_scans(packets: list[LidarPacket], clouds: list[PointCloud],
                decoding: Callable[[], OusterMetadata | VendorDecoding | None],
                every_n_scans: int, view_clouds: list[PointCloud] | None = None) -> LidarScans | None:
    """The scans the Lidar ground is taken from: the point clouds when there are any, else the packets decoded as
    `decoding()` says (asked for only then: the Ouster's metadata or a vendor decoding; None: packets that cannot
    be decoded, no scans). The viewing clouds (`lidar/view`, decoded from the same packets) only when the log holds
    neither, each of them (they are already a few scans a second): never both, so no scan counts twice."""
    if clouds:
        return point_cloud_scans(clouds, every_n_scans)
    how = decoding() if packets else None
    if isinstance(how, VendorDecoding):
        return vendor_packet_scans(packets, how, every_n_scans)
    if how is not None:
        return packet_scans(packets, how, every_n_scans)
    return point_cloud_scans(view_clouds, 1, LIDAR_VIEW) if view_clouds and not packets else None


def scans_ground(scans: LidarScans, clock: ClockMap, config: CarConfig, trajectory: Trajectory,
                 settings: GroundFilter, standing_t0_ns: int | None = None, progress: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, StandingPoints | None, np.ndarray]:
    """Ground points of the scans, in scan order, their firing times (seconds from the trajectory's start: what
    mapping.fits.lidar_registration re-places them with), their intensity contrast (intensity_contrast: what
    the registration aligns horizontally), and with `standing_t0_ns` the points standing on the
    road scan by scan (heights: `mapper.maskless`), each scan at the host time of its middle firing in seconds from
    standing_t0_ns (the keyframes' clock), else None (returned third, the contrast last). The scans are shared out over
    `mapper.runtime.lidar_ground_threads` threads (numpy releases the GIL in its array work); `progress`: a bar of
    the scans with its ETA on stderr."""
    T_vl = config.sensors.lidar.extrinsics.matrix()
    road = TrajectoryGround.of(trajectory, config.vehicle.reference_height_m, settings.corridor_half_width_m,
                               settings.ground_cell_m)
    heights = config.mapper.maskless

    bar = tqdm(total=len(scans.scans), desc="lidar ground", unit="scan", disable=not progress, mininterval=0.5)

    def scan_points(scan: object) -> tuple[np.ndarray, np.ndarray, tuple[float, np.ndarray] | None, np.ndarray]:
        bar.update()
        points = scans.decode(scan)
        world, seconds, index = lidar_world_points(points, clock, T_vl, trajectory, settings)
        on_ground = ground_index(world, road, settings)
        kept = index[on_ground]
        contrast = intensity_contrast(None if points.intensity is None else points.intensity[kept],
                                      np.linalg.norm(points.xyz[kept], axis=1))
        if standing_t0_ns is None or len(points.times_ns) == 0:
            return world[on_ground], seconds[on_ground], None, contrast
        middle = int(clock.to_host([int(points.times_ns[len(points.times_ns) // 2])])[0])
        return world[on_ground], seconds[on_ground], ((middle - standing_t0_ns) / 1e9, standing_points(
            world, road, heights.standing_min_m, heights.standing_max_m)), contrast

    with ThreadPoolExecutor(config.mapper.runtime.lidar_ground_threads, thread_name_prefix="lidar-ground") as pool:
        out = list(pool.map(scan_points, scans.scans))
    bar.close()
    ground = np.concatenate([g for g, _, _, _ in out]) if out else np.zeros((0, 3))
    times = np.concatenate([t for _, t, _, _ in out]) if out else np.zeros(0)
    contrast = np.concatenate([c for _, _, _, c in out]) if out else np.zeros(0, np.float32)
    if settings.static is not None:
        scan = np.repeat(np.arange(len(out)), [len(g) for g, _, _, _ in out])
        static = static_index(ground, scan, settings.static)
        ground, times, contrast = ground[static], times[static], contrast[static]
    if standing_t0_ns is None:
        return ground, times, None, contrast
    return ground, times, StandingPoints.of(sorted((s for _, _, s, _ in out if s is not None), key=lambda s: s[0])), \
        contrast
