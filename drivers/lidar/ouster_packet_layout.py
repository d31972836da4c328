"""Byte layout of Ouster lidar UDP packets for each UDP profile: where the packet header, the column
headers and every pixel field sit. The decoder reads and the encoder writes through this one table."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.lidar.ouster_metadata import OusterMetadata


@dataclass(frozen=True)
class PixelField:
    """One pixel field: `bits` bits starting at bit `shift` of the little-endian 32-bit word
    `word` of the pixel; the decoded value is that number shifted left by `upshift`."""

    word: int
    shift: int
    bits: int
    upshift: int = 0


# Pixel fields per profile, with the pixel size in bytes (Ouster sensor data manual, firmware 2.x/3.x).
_LB = {
    "range_mm": PixelField(0, 0, 15, 3),
    "reflectivity": PixelField(0, 16, 8),
    "near_ir": PixelField(0, 24, 8, 4),
}
_LB_DUAL = {
    **_LB,
    "range2_mm": PixelField(1, 0, 15, 3),
    "reflectivity2": PixelField(1, 16, 8),
}
_SINGLE = {
    "range_mm": PixelField(0, 0, 19),
    "reflectivity": PixelField(1, 0, 8),
    "signal": PixelField(1, 16, 16),
    "near_ir": PixelField(2, 0, 16),
}
PROFILE_PIXEL_FIELDS: dict[str, tuple[int, dict[str, PixelField]]] = {
    "LEGACY": (
        12,
        {
            "range_mm": PixelField(0, 0, 20),
            "reflectivity": PixelField(1, 0, 8),
            "signal": PixelField(1, 16, 16),
            "near_ir": PixelField(2, 0, 16),
        },
    ),
    "RNG19_RFL8_SIG16_NIR16": (12, _SINGLE),
    "RNG19_RFL8_SIG16_NIR16_DUAL": (
        16,
        {
            "range_mm": PixelField(0, 0, 19),
            "reflectivity": PixelField(0, 24, 8),
            "range2_mm": PixelField(1, 0, 19),
            "reflectivity2": PixelField(1, 24, 8),
            "signal": PixelField(2, 0, 16),
            "signal2": PixelField(2, 16, 16),
            "near_ir": PixelField(3, 0, 16),
        },
    ),
    "RNG15_RFL8_NIR8": (4, _LB),
    "RNG15_RFL8_NIR8_DUAL": (8, _LB_DUAL),
    "FUSA_RNG15_RFL8_NIR8_DUAL": (8, _LB_DUAL),
    # Zone-monitoring profiles: a 16-bit zone mask follows (not decoded).
    "RNG19_RFL8_SIG16_NIR16_ZONE16": (12, _SINGLE),
    "RNG15_RFL8_NIR8_ZONE16": (8, _LB),
}

LEGACY_ENCODER_TICKS_PER_REV = 90112


@dataclass(frozen=True)
class OusterPacketLayout:
    """Sizes and offsets (bytes) of one lidar packet; all offsets are multiples of 4."""

    profile: str
    legacy: bool  # LEGACY: no packet header, frame id in each column header, status after the pixels
    fusa: bool  # FuSa header: 8-bit packet type, 32-bit frame id
    columns_per_packet: int
    pixels_per_column: int
    columns_per_frame: int
    pixel_size: int
    pixel_fields: dict[str, PixelField]
    packet_header_size: int
    column_header_size: int
    column_footer_size: int
    packet_footer_size: int
    frame_id_modulus: int
    column_window: tuple[int, int]  # first and last measurement id the sensor sends, inclusive

    @property
    def column_size(self) -> int:
        return self.column_header_size + self.pixels_per_column * self.pixel_size + self.column_footer_size

    @property
    def packet_size(self) -> int:
        return self.packet_header_size + self.columns_per_packet * self.column_size + self.packet_footer_size

    @property
    def packets_per_frame(self) -> int:
        return self.columns_per_frame // self.columns_per_packet

    @property
    def window_packets(self) -> tuple[int, int]:
        """(first packet number in the column window, number of packets per frame it spans)."""
        first = self.column_window[0] // self.columns_per_packet
        last = self.column_window[1] // self.columns_per_packet
        return first, (last - first) % self.packets_per_frame + 1

    @property
    def column_status_offset(self) -> int:
        """Offset of the column status within a column: a 32-bit footer (LEGACY) or the 16-bit
        word after the measurement id; bit 0 set means the column holds valid data."""
        return self.column_size - 4 if self.legacy else 10


def packet_layout(meta: OusterMetadata) -> OusterPacketLayout:
    if meta.udp_profile_lidar not in PROFILE_PIXEL_FIELDS:
        raise ValueError(
            f"no packet layout for UDP profile {meta.udp_profile_lidar!r}; known: {sorted(PROFILE_PIXEL_FIELDS)}"
        )
    pixel_size, fields = PROFILE_PIXEL_FIELDS[meta.udp_profile_lidar]
    legacy = meta.udp_profile_lidar == "LEGACY"
    layout = OusterPacketLayout(
        profile=meta.udp_profile_lidar,
        legacy=legacy,
        fusa=meta.header_type == "FUSA" and not legacy,
        columns_per_packet=meta.columns_per_packet,
        pixels_per_column=meta.pixels_per_column,
        columns_per_frame=meta.columns_per_frame,
        pixel_size=pixel_size,
        pixel_fields=fields,
        packet_header_size=0 if legacy else 32,
        column_header_size=16 if legacy else 12,
        column_footer_size=4 if legacy else 0,
        packet_footer_size=0 if legacy else 32,
        frame_id_modulus=meta.frame_id_modulus,
        column_window=meta.column_window,
    )
    if layout.packet_size > 65535:
        raise ValueError(f"Ouster lidar packet of {layout.packet_size} bytes exceeds a UDP datagram")
    return layout


def packets_per_second(metadata: OusterMetadata) -> float:
    """The packet rate the sensor sends: the packets of its column window, fps times a second."""
    return float(packet_layout(metadata).window_packets[1] * metadata.fps)
