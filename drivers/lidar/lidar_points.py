"""Data shapes shared by every lidar decoder (Ouster now; Hesai, Velodyne the same way): a decoded
batch of packets as (packets, columns, pixels) arrays, its error counts, the XYZ lookup table, one
assembled scan and its point cloud; and the conversions from ranges to points."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass
class PacketDecodeCounts:
    """What happened to the datagrams of one decode call; packets_in is always the sum of the
    three packet outcomes."""

    packets_in: int = 0
    packets_decoded: int = 0
    wrong_size: int = 0  # length is not the profile's packet size
    bad_header: int = 0  # packet type, serial number, frame id or measurement ids inconsistent
    invalid_columns: int = 0  # columns of decoded packets whose status says "no data"

    def add(self, other: PacketDecodeCounts) -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))


@dataclass
class LidarPacketBatch:
    """The good packets of one decode call. P packets, K columns per packet, H pixels per column.

    A column is one firing of all H beams at one azimuth; `column_index` is its place in the frame
    (Ouster measurement id; for sensors without one, the azimuth bin). Second-return arrays are None
    for single-return profiles, signal/near_ir for profiles without them."""

    packet_index: np.ndarray  # (P,) int64, position of each packet in the decoder's input
    frame_id: np.ndarray  # (P,) int64
    column_index: np.ndarray  # (P, K) int32
    timestamp_ns: np.ndarray  # (P, K) uint64, sensor clock
    column_valid: np.ndarray  # (P, K) bool
    range_mm: np.ndarray  # (P, K, H) uint32, 0 = no return
    reflectivity: np.ndarray  # (P, K, H) uint8
    signal: np.ndarray | None  # (P, K, H) uint16
    near_ir: np.ndarray | None  # (P, K, H) uint16
    range2_mm: np.ndarray | None  # (P, K, H) uint32
    reflectivity2: np.ndarray | None  # (P, K, H) uint8
    signal2: np.ndarray | None  # (P, K, H) uint16
    counts: PacketDecodeCounts

    @property
    def num_packets(self) -> int:
        return int(self.frame_id.shape[0])

    def select(self, packets: np.ndarray) -> LidarPacketBatch:
        """The sub-batch of the given packets (boolean mask or indices over P)."""

        def pick(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[packets]

        return LidarPacketBatch(
            packet_index=self.packet_index[packets],
            frame_id=self.frame_id[packets],
            column_index=self.column_index[packets],
            timestamp_ns=self.timestamp_ns[packets],
            column_valid=self.column_valid[packets],
            range_mm=self.range_mm[packets],
            reflectivity=self.reflectivity[packets],
            signal=pick(self.signal),
            near_ir=pick(self.near_ir),
            range2_mm=pick(self.range2_mm),
            reflectivity2=pick(self.reflectivity2),
            signal2=pick(self.signal2),
            counts=PacketDecodeCounts(),
        )


@dataclass
class XYZLut:
    """Per (column, beam) unit direction and offset, so that point = direction * range + offset.

    Planar float32 arrays of shape (3, W, H), metres per millimetre of range and metres; the
    same transposed to (3, H, W) for scan images."""

    direction: np.ndarray
    offset: np.ndarray

    def __post_init__(self) -> None:
        self.direction_image = np.ascontiguousarray(self.direction.transpose(0, 2, 1))
        self.offset_image = np.ascontiguousarray(self.offset.transpose(0, 2, 1))

    @property
    def columns_per_frame(self) -> int:
        return int(self.direction.shape[1])


def _lut_columns(lut: XYZLut, column_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """direction, offset for the (P, K) columns as (3, P, K, H): a view when the columns run on
    without a gap, as they do for the packets of a frame in order, otherwise a gathered copy."""
    p, k = column_index.shape
    h = lut.direction.shape[2]
    if p:
        first = int(column_index[0, 0])
        if first + p * k <= lut.columns_per_frame and np.array_equal(
            column_index.ravel(), np.arange(first, first + p * k)
        ):
            cols = slice(first, first + p * k)
            return (
                lut.direction[:, cols].reshape(3, p, k, h),
                lut.offset[:, cols].reshape(3, p, k, h),
            )
    return lut.direction[:, column_index], lut.offset[:, column_index]


def batch_xyz(batch: LidarPacketBatch, lut: XYZLut, range_mm: np.ndarray | None = None) -> np.ndarray:
    """Points of every pixel of the batch, (P, K, H, 3) float32 metres in the LUT's frame; a pixel
    with no return gives (0, 0, 0). A planar array underneath: the result is a strided view.

    `range_mm` defaults to the first return; pass batch.range2_mm for the second."""
    r = batch.range_mm if range_mm is None else range_mm
    direction, offset = _lut_columns(lut, batch.column_index)
    rf = r.astype(np.float32)
    xyz = np.multiply(direction, rf)
    np.add(xyz, offset, out=xyz)
    np.multiply(xyz, r != 0, out=xyz)
    return np.moveaxis(xyz, 0, -1)


@dataclass
class LidarScan:
    """One frame (full rotation) assembled from packets, as staggered H x W images like the
    sensor's: column w of every image holds the pixels of measurement w. Missing or invalid columns
    hold zeros and column_valid False."""

    frame_id: int
    packets_received: int
    packets_expected: int
    timestamp_ns: np.ndarray  # (W,) uint64
    column_valid: np.ndarray  # (W,) bool
    range_mm: np.ndarray  # (H, W) uint32
    reflectivity: np.ndarray  # (H, W) uint8
    signal: np.ndarray | None  # (H, W) uint16
    near_ir: np.ndarray | None  # (H, W) uint16
    range2_mm: np.ndarray | None  # (H, W) uint32

    @property
    def complete(self) -> bool:
        return self.packets_received == self.packets_expected


@dataclass
class LidarPointCloud:
    """The points with a return of one scan, N of them, in the LUT's frame."""

    frame_id: int
    xyz: np.ndarray  # (N, 3) float32 metres
    range_mm: np.ndarray  # (N,) uint32
    reflectivity: np.ndarray  # (N,) uint8
    ring: np.ndarray  # (N,) uint16, beam index, 0 = top beam
    column: np.ndarray  # (N,) uint16, column (measurement id) in the frame
    timestamp_ns: np.ndarray  # (N,) uint64, time of the point's column


def scan_point_cloud(scan: LidarScan, lut: XYZLut) -> LidarPointCloud:
    """Points of the valid pixels (valid column, range > 0) of a scan, ordered by ring then column."""
    w = scan.range_mm.shape[1]
    keep = np.flatnonzero(((scan.range_mm != 0) & scan.column_valid[None, :]).ravel())
    ring, column = np.divmod(keep, w)
    r = scan.range_mm.ravel()[keep]
    planar = lut.direction_image.reshape(3, -1).take(keep, axis=1)
    planar *= r.astype(np.float32)
    planar += lut.offset_image.reshape(3, -1).take(keep, axis=1)
    return LidarPointCloud(
        frame_id=scan.frame_id,
        xyz=np.ascontiguousarray(planar.T),
        range_mm=r,
        reflectivity=scan.reflectivity.ravel()[keep],
        ring=ring.astype(np.uint16),
        column=column.astype(np.uint16),
        timestamp_ns=scan.timestamp_ns[column],
    )


def destagger(image: np.ndarray, pixel_shift_by_row: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Roll row u of an (H, W, ...) image right by pixel_shift_by_row[u] columns (left if inverse),
    turning the staggered image of a scan into one where each column looks in one direction."""
    h, w = image.shape[:2]
    shifts = np.asarray(pixel_shift_by_row, dtype=np.int64)
    if inverse:
        shifts = -shifts
    source_columns = (np.arange(w)[None, :] - shifts[:, None]) % w
    return image[np.arange(h)[:, None], source_columns]
