"""Vectorised decoder of Ouster lidar UDP packets: a batch of datagrams in, one LidarPacketBatch
out, bad datagrams counted and skipped; and packet-loss counting from frame and measurement ids."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from drivers.lidar.lidar_points import LidarPacketBatch, PacketDecodeCounts
from drivers.lidar.ouster_packet_layout import OusterPacketLayout, PixelField
from drivers.lidar.scan_assembler import ScanAssembler

LIDAR_PACKET_TYPE = 1

_FIELD_DTYPES = {
    "range_mm": np.uint32,
    "range2_mm": np.uint32,
    "reflectivity": np.uint8,
    "reflectivity2": np.uint8,
    "signal": np.uint16,
    "signal2": np.uint16,
    "near_ir": np.uint16,
}


def _view(buf: np.ndarray, dtype: str, offset: int, shape: tuple, strides: tuple) -> np.ndarray:
    """A strided view of `dtype` values into the C-contiguous uint8 array `buf` (bounds checked)."""
    return np.ndarray(shape, dtype=dtype, buffer=buf, offset=offset, strides=strides)


def _column_view(buf: np.ndarray, layout: OusterPacketLayout, dtype: str, offset: int) -> np.ndarray:
    """(P, K) values at byte `offset` of every column."""
    return _view(
        buf,
        dtype,
        layout.packet_header_size + offset,
        (buf.shape[0], layout.columns_per_packet),
        (layout.packet_size, layout.column_size),
    )


def _packet_view(buf: np.ndarray, layout: OusterPacketLayout, dtype: str, offset: int) -> np.ndarray:
    """(P,) values at byte `offset` of every packet."""
    return _view(buf, dtype, offset, (buf.shape[0],), (layout.packet_size,))


def _pixel_field(buf: np.ndarray, layout: OusterPacketLayout, field: PixelField, dtype) -> np.ndarray:
    """(P, K, H) values of one pixel field."""
    shape = (buf.shape[0], layout.columns_per_packet, layout.pixels_per_column)
    strides = (layout.packet_size, layout.column_size, layout.pixel_size)
    offset = layout.packet_header_size + layout.column_header_size + 4 * field.word
    if field.upshift == 0 and field.shift % 8 == 0 and field.bits in (8, 16):
        raw = _view(buf, f"<u{field.bits // 8}", offset + field.shift // 8, shape, strides)
        return raw.astype(dtype)
    words = _view(buf, "<u4", offset, shape, strides)
    if field.shift:
        words = words >> np.uint32(field.shift)
    values = np.bitwise_and(words, np.uint32((1 << field.bits) - 1))
    if field.upshift:
        values <<= np.uint32(field.upshift)
    return values.astype(dtype, copy=False)


def _as_packet_rows(
    datagrams: np.ndarray | Sequence[bytes | bytearray | memoryview],
    sizes: np.ndarray | None,
    packet_size: int,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The datagrams of the right size as a C-contiguous (P, packet_size) uint8 array, their indices
    in the input, and the number of datagrams in."""
    if isinstance(datagrams, np.ndarray):
        rows = datagrams
        n = rows.shape[0]
        lengths = np.full(n, rows.shape[-1]) if sizes is None else np.asarray(sizes)
        if rows.ndim != 2 or rows.dtype != np.uint8 or lengths.shape != (n,):
            raise TypeError("datagrams must be a (N, S) uint8 array with sizes of shape (N,)")
        if rows.shape[1] < packet_size:
            return np.zeros((0, packet_size), np.uint8), np.zeros(0, np.int64), n
        index = np.flatnonzero(lengths == packet_size)
        good = rows[:, :packet_size]
        if len(index) < n:
            good = good[index]
        return np.ascontiguousarray(good), index, n
    n = len(datagrams)
    index = np.array([i for i, d in enumerate(datagrams) if len(d) == packet_size], dtype=np.int64)
    joined = b"".join(datagrams[i] for i in index)
    rows = np.frombuffer(joined, dtype=np.uint8).reshape(len(index), packet_size)
    return rows, index, n


def _make_batch(
    index: np.ndarray,
    frame_id: np.ndarray,
    column_index: np.ndarray,
    timestamp: np.ndarray,
    valid: np.ndarray,
    pixels: dict[str, np.ndarray],
    counts: PacketDecodeCounts,
) -> LidarPacketBatch:
    return LidarPacketBatch(
        packet_index=index.astype(np.int64),
        frame_id=frame_id,
        column_index=column_index,
        timestamp_ns=timestamp,
        column_valid=valid,
        range_mm=pixels["range_mm"],
        reflectivity=pixels["reflectivity"],
        signal=pixels.get("signal"),
        near_ir=pixels.get("near_ir"),
        range2_mm=pixels.get("range2_mm"),
        reflectivity2=pixels.get("reflectivity2"),
        signal2=pixels.get("signal2"),
        counts=counts,
    )


def _empty_batch(layout: OusterPacketLayout, counts: PacketDecodeCounts) -> LidarPacketBatch:
    k, h = layout.columns_per_packet, layout.pixels_per_column
    pixels = {name: np.zeros((0, k, h), _FIELD_DTYPES[name]) for name in layout.pixel_fields}
    return _make_batch(
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, k), np.int32),
        np.zeros((0, k), np.uint64),
        np.zeros((0, k), bool),
        pixels,
        counts,
    )


def decode_packets(
    datagrams: np.ndarray | Sequence[bytes | bytearray | memoryview],
    layout: OusterPacketLayout,
    sizes: np.ndarray | None = None,
    prod_sn: int | None = None,
) -> LidarPacketBatch:
    """Decode a batch of lidar datagrams; never raises on their content.

    `datagrams` is a sequence of byte strings, or an (N, S) uint8 array of receive buffers with the
    received lengths in `sizes`. A datagram is skipped and counted when its length is not the
    profile's packet size (wrong_size) or when its header does not hold together (bad_header):
    packet type not lidar, serial number not `prod_sn` (when given), LEGACY frame ids differing
    between valid columns, or measurement ids of the valid columns not first+0, first+1, ... inside
    the frame. Columns whose status bit 0 is clear are kept with column_valid False, counted."""
    rows, index, n_in = _as_packet_rows(datagrams, sizes, layout.packet_size)
    n_sized = len(rows)
    if n_sized == 0:
        return _empty_batch(layout, PacketDecodeCounts(packets_in=n_in, wrong_size=n_in))
    k = layout.columns_per_packet
    status_dtype = "<u4" if layout.legacy else "<u2"
    status = _column_view(rows, layout, status_dtype, layout.column_status_offset)
    valid = (status & 1).astype(bool)
    measurement_id = _column_view(rows, layout, "<u2", 8).astype(np.int64)

    # Column k of a packet must be measurement first + k; columns without data may hold anything.
    first_valid = np.argmax(valid, axis=1)
    base_all = measurement_id - np.arange(k)
    base = base_all[np.arange(n_sized), first_valid]
    ok = np.all((base_all == base[:, None]) | ~valid, axis=1)
    ok &= (base >= 0) & (base <= layout.columns_per_frame - k)

    if layout.legacy:
        column_frame_id = _column_view(rows, layout, "<u2", 10)
        frame_id = column_frame_id[:, 0].astype(np.int64)
        ok &= np.all((column_frame_id == column_frame_id[:, :1]) | ~valid, axis=1)
    elif layout.fusa:
        frame_id = _packet_view(rows, layout, "<u4", 4).astype(np.int64)
        ok &= _packet_view(rows, layout, "u1", 0) == LIDAR_PACKET_TYPE
    else:
        frame_id = _packet_view(rows, layout, "<u2", 2).astype(np.int64)
        ok &= _packet_view(rows, layout, "<u2", 0) == LIDAR_PACKET_TYPE
    if prod_sn is not None and not layout.legacy:
        sn_offset = 11 if layout.fusa else 7
        sn_bytes = rows[:, sn_offset : sn_offset + 5].astype(np.uint64)
        sn = (sn_bytes << (np.arange(5, dtype=np.uint64) * np.uint64(8))).sum(axis=1)
        ok &= sn == np.uint64(prod_sn)

    counts = PacketDecodeCounts(
        packets_in=n_in,
        packets_decoded=int(np.count_nonzero(ok)),
        wrong_size=n_in - n_sized,
        bad_header=int(n_sized - np.count_nonzero(ok)),
    )
    if counts.bad_header:
        keep = np.flatnonzero(ok)
        rows, index = rows[keep], index[keep]
        frame_id, valid, base = frame_id[keep], valid[keep], base[keep]
        if len(rows) == 0:
            return _empty_batch(layout, counts)
    counts.invalid_columns = int(valid.size - np.count_nonzero(valid))
    timestamp = _column_view(rows, layout, "<u8", 0).astype(np.uint64)
    column_index = (base[:, None] + np.arange(k)).astype(np.int32)
    pixels = {
        name: _pixel_field(rows, layout, field, _FIELD_DTYPES[name]) for name, field in layout.pixel_fields.items()
    }
    return _make_batch(index, frame_id, column_index, timestamp, valid, pixels, counts)


def packet_sequence(batch: LidarPacketBatch, layout: OusterPacketLayout) -> np.ndarray:
    """(P,) int64 position of each packet in the sensor's endless packet stream, modulo
    layout.frame_id_modulus * packets per frame: consecutive packets differ by exactly one."""
    first, per_frame = layout.window_packets
    ordinal = (batch.column_index[:, 0].astype(np.int64) // layout.columns_per_packet - first) % (
        layout.packets_per_frame
    )
    return batch.frame_id * per_frame + np.minimum(ordinal, per_frame - 1)


def _steps_ahead(sequence: np.ndarray, layout: OusterPacketLayout, reference: int) -> np.ndarray:
    """How far each sequence number is ahead of `reference`, negative for behind (wrap-aware)."""
    modulus = layout.frame_id_modulus * layout.window_packets[1]
    step = (np.asarray(sequence, dtype=np.int64) - reference) % modulus
    return np.where(step > modulus // 2, step - modulus, step)


def count_missing_packets(sequence: np.ndarray, layout: OusterPacketLayout, previous: int | None = None) -> int:
    """Packets never seen between `previous` (the newest sequence number of earlier batches, see
    newest_packet; else the first of this one) and the newest packet of `sequence` (from
    packet_sequence). Reordered and repeated packets are not losses; a packet older than the
    reference is ignored."""
    if len(sequence) == 0:
        return 0
    reference = int(sequence[0]) if previous is None else previous
    ahead = _steps_ahead(sequence, layout, reference)
    ahead = np.unique(ahead[ahead > 0])
    return int(ahead[-1] - len(ahead)) if len(ahead) else 0


def newest_packet(sequence: np.ndarray, layout: OusterPacketLayout, previous: int | None = None) -> int | None:
    """The newest sequence number seen in `sequence` and `previous` together: the `previous` to
    pass with the next batch."""
    if len(sequence) == 0:
        return previous
    reference = int(sequence[0]) if previous is None else previous
    modulus = layout.frame_id_modulus * layout.window_packets[1]
    return (reference + max(0, int(_steps_ahead(sequence, layout, reference).max()))) % modulus


def ouster_scan_assembler(layout: OusterPacketLayout) -> ScanAssembler:
    """A ScanAssembler for this sensor's frames (complete = every packet of the column window)."""
    return ScanAssembler(
        columns_per_frame=layout.columns_per_frame,
        pixels_per_column=layout.pixels_per_column,
        columns_per_packet=layout.columns_per_packet,
        packets_per_frame=layout.window_packets[1],
        frame_id_modulus=layout.frame_id_modulus,
    )
