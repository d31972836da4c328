"""Encode one frame of ranges (and reflectivity, signal, near-IR) into real Ouster lidar UDP packets,
for the simulator: the inverse of ouster_decoder, through the same packet layout table."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from drivers.lidar.ouster_decoder import LIDAR_PACKET_TYPE
from drivers.lidar.ouster_packet_layout import LEGACY_ENCODER_TICKS_PER_REV, OusterPacketLayout


def _writable_view(buf: np.ndarray, dtype: str, offset: int, shape: tuple, strides: tuple) -> np.ndarray:
    return np.ndarray(shape, dtype=dtype, buffer=buf, offset=offset, strides=strides)


def encode_frame_packets(
    layout: OusterPacketLayout,
    frame_id: int,
    pixels: Mapping[str, np.ndarray],
    timestamp_ns: np.ndarray,
    column_valid: np.ndarray | None = None,
    init_id: int = 0,
    prod_sn: int = 0,
) -> np.ndarray:
    """The packets of one frame as a (W / K, packet_size) uint8 array, packet p holding columns
    p*K .. p*K+K-1.

    `pixels` maps pixel field names of the layout ("range_mm", "reflectivity", "signal",
    "near_ir", second-return names for dual profiles) to staggered (H, W) images: column w is
    measurement w, as the sensor fires it; fields left out are sent as zero. Values beyond a
    field's range are clipped to its maximum; low-data profiles drop the range's low 3 bits.
    `timestamp_ns` is each column's (W,) sensor time; columns with column_valid False are sent
    with status 0 and no data. `init_id` and `prod_sn` go into non-LEGACY packet headers."""
    h, w, k = layout.pixels_per_column, layout.columns_per_frame, layout.columns_per_packet
    p = w // k
    unknown = set(pixels) - set(layout.pixel_fields)
    if unknown:
        raise ValueError(f"profile {layout.profile} has no pixel fields {sorted(unknown)}")
    valid = np.ones(w, bool) if column_valid is None else np.asarray(column_valid, bool)
    buf = np.zeros((p, layout.packet_size), np.uint8)

    words = _writable_view(
        buf,
        "<u4",
        layout.packet_header_size + layout.column_header_size,
        (p, k, h, layout.pixel_size // 4),
        (layout.packet_size, layout.column_size, layout.pixel_size, 4),
    )
    for name, image in pixels.items():
        field = layout.pixel_fields[name]
        values = np.asarray(image).astype(np.int64).T * valid[:, None]  # (W, H), zero where invalid
        top = (1 << field.bits) - 1
        raw = np.clip(values >> field.upshift, 0, top).astype(np.uint32) << np.uint32(field.shift)
        words[..., field.word] |= raw.reshape(p, k, h)

    def column(dtype: str, offset: int) -> np.ndarray:
        return _writable_view(
            buf, dtype, layout.packet_header_size + offset, (p, k), (layout.packet_size, layout.column_size)
        )

    measurement_id = np.arange(w).reshape(p, k)
    column("<u8", 0)[:] = np.asarray(timestamp_ns, np.uint64).reshape(p, k)
    column("<u2", 8)[:] = measurement_id
    if layout.legacy:
        column("<u2", 10)[:] = frame_id % layout.frame_id_modulus
        column("<u4", 12)[:] = measurement_id * LEGACY_ENCODER_TICKS_PER_REV // w
        column("<u4", layout.column_status_offset)[:] = np.where(valid, 0xFFFFFFFF, 0).reshape(p, k)
        return buf
    column("<u2", layout.column_status_offset)[:] = valid.reshape(p, k)
    frame = frame_id % layout.frame_id_modulus
    if layout.fusa:
        buf[:, 0] = LIDAR_PACKET_TYPE
        buf[:, 1:4] = np.frombuffer(init_id.to_bytes(3, "little"), np.uint8)
        buf[:, 4:8] = np.frombuffer(frame.to_bytes(4, "little"), np.uint8)
        buf[:, 11:16] = np.frombuffer(prod_sn.to_bytes(5, "little"), np.uint8)
    else:
        buf[:, 0:2] = np.frombuffer(LIDAR_PACKET_TYPE.to_bytes(2, "little"), np.uint8)
        buf[:, 2:4] = np.frombuffer(frame.to_bytes(2, "little"), np.uint8)
        buf[:, 4:7] = np.frombuffer(init_id.to_bytes(3, "little"), np.uint8)
        buf[:, 7:12] = np.frombuffer(prod_sn.to_bytes(5, "little"), np.uint8)
    return buf


def packet_frame_id(packet: bytes, layout: OusterPacketLayout) -> int:
    """The frame id a packet carries (LEGACY: its first column's; otherwise its header's)."""
    if layout.legacy:
        return int.from_bytes(packet[10:12], "little")
    return int.from_bytes(packet[4:8] if layout.fusa else packet[2:4], "little")


def renumbered_packet(packet: bytes, layout: OusterPacketLayout, frame_id_offset: int, time_offset_ns: int) -> bytes:
    """The same packet, `frame_id_offset` frames and `time_offset_ns` later (frame ids modulo the layout's):
    a recorded stretch of packets sent again as the sensor would go on sending (the simulator's looped drive)."""
    buf = np.frombuffer(packet, np.uint8).copy()[None]
    k, size = layout.columns_per_packet, layout.column_size
    times = _writable_view(buf, "<u8", layout.packet_header_size, (1, k), (layout.packet_size, size))
    times += np.uint64(time_offset_ns)
    frame = (packet_frame_id(packet, layout) + frame_id_offset) % layout.frame_id_modulus
    if layout.legacy:
        _writable_view(buf, "<u2", 10, (1, k), (layout.packet_size, size))[:] = frame
    elif layout.fusa:
        buf[0, 4:8] = np.frombuffer(frame.to_bytes(4, "little"), np.uint8)
    else:
        buf[0, 2:4] = np.frombuffer(frame.to_bytes(2, "little"), np.uint8)
    return buf.tobytes()
