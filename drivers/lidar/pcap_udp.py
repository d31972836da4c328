"""Read the UDP datagrams of a classic pcap capture (Ethernet, optional VLAN tags, IPv4 or IPv6),
to replay recorded lidar packets. IP fragments are not reassembled: they are counted and skipped."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

_PCAP_MAGIC = {
    b"\xd4\xc3\xb2\xa1": ("<", 1000),  # microsecond time stamps, little-endian
    b"\xa1\xb2\xc3\xd4": (">", 1000),
    b"\x4d\x3c\xb2\xa1": ("<", 1),  # nanosecond time stamps
    b"\xa1\xb2\x3c\x4d": (">", 1),
}
_LINKTYPE_ETHERNET = 1
_ETH_IPV4, _ETH_IPV6, _ETH_VLAN, _ETH_QINQ = 0x0800, 0x86DD, 0x8100, 0x88A8
_IP_UDP = 17


@dataclass
class UdpDatagram:
    timestamp_ns: int  # capture time
    src_port: int
    dst_port: int
    payload: bytes


@dataclass
class PcapUdpCapture:
    datagrams: list[UdpDatagram] = field(default_factory=list)
    skipped_not_udp: int = 0
    skipped_fragments: int = 0
    skipped_truncated: int = 0


def _udp_at(frame: bytes, offset: int) -> tuple[int, int, bytes] | str:
    """(src port, dst port, payload) of the UDP header at `offset`, or why there is none."""
    if len(frame) < offset + 8:
        return "truncated"
    src, dst, length = struct.unpack_from(">HHH", frame, offset)
    if length < 8 or offset + length > len(frame):
        return "truncated"
    return src, dst, frame[offset + 8 : offset + length]


def _parse_ethernet(frame: bytes) -> tuple[int, int, bytes] | str:
    offset, ethertype = 14, struct.unpack_from(">H", frame, 12)[0] if len(frame) >= 14 else None
    while ethertype in (_ETH_VLAN, _ETH_QINQ) and len(frame) >= offset + 4:
        ethertype = struct.unpack_from(">H", frame, offset + 2)[0]
        offset += 4
    if ethertype == _ETH_IPV4 and len(frame) >= offset + 20:
        header_len = (frame[offset] & 0x0F) * 4
        flags_fragment = struct.unpack_from(">H", frame, offset + 6)[0]
        if frame[offset + 9] != _IP_UDP:
            return "not_udp"
        if flags_fragment & 0x3FFF:  # more-fragments flag or a fragment offset
            return "fragments"
        return _udp_at(frame, offset + header_len)
    if ethertype == _ETH_IPV6 and len(frame) >= offset + 40:
        if frame[offset + 6] == 44:
            return "fragments"
        if frame[offset + 6] != _IP_UDP:
            return "not_udp"
        return _udp_at(frame, offset + 40)
    return "truncated" if ethertype is None else "not_udp"


def read_pcap_udp(path: str | Path, dst_port: int | None = None) -> PcapUdpCapture:
    """All UDP datagrams of a pcap file (only those to `dst_port` when given), in capture order."""
    data = Path(path).read_bytes()
    if len(data) < 24 or data[:4] not in _PCAP_MAGIC:
        raise ValueError(f"{path}: not a classic pcap file (pcapng is not supported)")
    endian, ns_per_tick = _PCAP_MAGIC[data[:4]]
    (linktype,) = struct.unpack_from(endian + "I", data, 20)
    if linktype != _LINKTYPE_ETHERNET:
        raise ValueError(f"{path}: link type {linktype} is not Ethernet")
    capture = PcapUdpCapture()
    offset = 24
    record = struct.Struct(endian + "IIII")
    while offset + 16 <= len(data):
        seconds, ticks, captured_len, _ = record.unpack_from(data, offset)
        offset += 16
        frame = data[offset : offset + captured_len]
        offset += captured_len
        parsed = _parse_ethernet(frame)
        if isinstance(parsed, str):
            setattr(capture, f"skipped_{parsed}", getattr(capture, f"skipped_{parsed}") + 1)
            continue
        src, dst, payload = parsed
        if dst_port is None or dst == dst_port:
            capture.datagrams.append(UdpDatagram(seconds * 1_000_000_000 + ticks * ns_per_tick, src, dst, payload))
    if offset != len(data):
        capture.skipped_truncated += 1
    return capture
