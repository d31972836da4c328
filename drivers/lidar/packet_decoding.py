"""What a Lidar packet decoder of any vendor but Ouster gives (Velodyne, Hesai, RoboSense): the check of each
datagram that the driver stamps and counts packets with (PacketCheck), the points of a batch of packets
(DecodedPoints), and where one rotation ends and the next begins (rotation_starts); for the decoders, a batch's
datagrams as one array (packet_batch) and the arrays their compiled loops fill (points_buffer, reused on a thread
once nothing holds the points made of them).

A decoder is an object with `model` (its name), `check(packets) -> PacketCheck` and
`decode(packets) -> DecodedPoints`; `packets` is a list of datagram payloads of any size, in arrival order.
Times are on the sensor's clock as its packets carry it (Velodyne: past the top of the hour; Hesai and
RoboSense: UTC), so a point's time after its packet's stamp is `timestamp_ns - packet_time_ns[packet_index]`.
"""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

# Bits of DecodedPoints.return_type; a dual-return point whose two returns agree carries both.
RETURN_TYPE_STRONGEST, RETURN_TYPE_LAST, RETURN_TYPE_OTHER = 1, 2, 4


@dataclass
class PacketCheck:
    """Each datagram of a batch looked at without decoding its points: whether it is one of this sensor's data
    packets, and then its stamp and the azimuth of its first firing."""

    accepted: np.ndarray  # (P,) bool
    sensor_time_ns: np.ndarray  # (P,) int64, the packet's own stamp on the sensor's clock; 0 where not accepted
    azimuth_cdeg: np.ndarray  # (P,) int32, its first firing's azimuth in 0.01 degrees, 0-35999; 0 where not
    counts: dict[str, int] = field(default_factory=dict)  # reason -> datagrams not accepted for it (nonzero only)


@dataclass
class DecodedPoints:
    """The returns with a range inside the decoder's limits of one decode call, in packet order."""

    model: str | None  # None when no packet decoded
    xyz: np.ndarray  # (N, 3) float32 metres, sensor frame (x forward, y left, z up)
    distance_m: np.ndarray  # (N,) float32, corrected range
    intensity: np.ndarray  # (N,) float32, as the sensor reports it (0-255 for most)
    laser_id: np.ndarray  # (N,) uint16, channel in the packet
    ring: np.ndarray  # (N,) uint16, rank of the laser by elevation, 0 = lowest
    azimuth_cdeg: np.ndarray  # (N,) uint16, the firing's azimuth before per-laser corrections, 0.01 degrees
    return_type: np.ndarray  # (N,) uint8, RETURN_TYPE_* bits
    timestamp_ns: np.ndarray  # (N,) int64, firing time on the sensor's clock
    packet_index: np.ndarray  # (N,) int64, position of the point's packet in the decode call's input
    packet_time_ns: np.ndarray  # (P,) int64, each input packet's own stamp as PacketCheck's; 0 where not decoded
    # packets_in, packets_decoded, and reason -> datagrams skipped for it
    counts: dict[str, int] = field(default_factory=dict)


class PacketDecoder(Protocol):
    model: str

    def check(self, packets: list[bytes]) -> PacketCheck: ...

    def decode(self, packets: list[bytes]) -> DecodedPoints: ...


def empty_points(counts: dict[str, int], model: str | None) -> DecodedPoints:
    return DecodedPoints(
        model=model,
        xyz=np.zeros((0, 3), np.float32),
        distance_m=np.zeros(0, np.float32),
        intensity=np.zeros(0, np.float32),
        laser_id=np.zeros(0, np.uint16),
        ring=np.zeros(0, np.uint16),
        azimuth_cdeg=np.zeros(0, np.uint16),
        return_type=np.zeros(0, np.uint8),
        timestamp_ns=np.zeros(0, np.int64),
        packet_index=np.zeros(0, np.int64),
        packet_time_ns=np.zeros(counts.get("packets_in", 0), np.int64),
        counts=counts,
    )


def packet_batch(packets: list[bytes], sizes: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The datagrams whose length is one of `sizes` as one (n, width) uint8 array, and their positions in `packets`.
    When they all have one length that is the width (the rows joined as they are: a longer size's optional trailing
    fields stay at the end of each row); otherwise the smallest size, longer ones cut to it."""
    lengths = np.fromiter(map(len, packets), np.int64, len(packets))
    sized = lengths == sizes[0]
    for size in sizes[1:]:  # (np.isin costs more than the rest for a few sizes)
        sized |= lengths == size
    index = np.flatnonzero(sized)
    if len(index) == 0:
        return np.zeros((0, min(sizes)), np.uint8), index
    width = int(lengths[index[0]])
    if np.all(lengths[index] == width):
        joined = b"".join(packets if len(index) == len(packets) else [packets[i] for i in index])
    else:
        width = min(sizes)
        joined = b"".join([packets[i][:width] for i in index])
    return np.frombuffer(joined, np.uint8).reshape(-1, width), index


def _new_points_buffer(capacity: int) -> tuple[np.ndarray, ...]:
    return (np.empty((capacity, 3), np.float32), np.empty(capacity, np.float32), np.empty(capacity, np.float32),
            np.empty(capacity, np.uint16), np.empty(capacity, np.uint16), np.empty(capacity, np.uint16),
            np.empty(capacity, np.uint8), np.empty(capacity, np.int64), np.empty(capacity, np.int64))


def _references(buffer: tuple[np.ndarray, ...]) -> list[int]:
    return [sys.getrefcount(a) for a in buffer]


_FREE_REFERENCES = _references(_new_points_buffer(0))  # a buffer only its tuple holds, as this interpreter counts
_reusable = threading.local()  # .buffer: this thread's last points_buffer


def points_buffer(capacity: int) -> tuple[np.ndarray, ...]:
    """Uninitialised arrays for at least `capacity` points that a compiled decode loop fills, in DecodedPoints' order:
    xyz, distance_m, intensity, laser_id, ring, azimuth_cdeg, return_type, timestamp_ns, packet_index.

    The last call's arrays on this thread when nothing else references them any more (every DecodedPoints and view
    made of them dropped) and they are large enough; otherwise new ones, kept for the next call. New memory is
    faulted in page by page as the loop writes it: that was 40 % of a VLS-128 decode here (bench/lidar.py)."""
    last = getattr(_reusable, "buffer", None)
    if last is not None and len(last[1]) >= capacity and _references(last) == _FREE_REFERENCES:
        return last
    _reusable.buffer = _new_points_buffer(capacity)
    return _reusable.buffer


def filled_points(model: str, buffer: tuple[np.ndarray, ...], n: int, n_packets: int, index: np.ndarray,
                  stamps_ns: np.ndarray) -> DecodedPoints:
    """The first n points of a points_buffer as DecodedPoints (views; counts left for the decoder to set), of n_packets
    input packets of which those at `index` decoded with their own stamps `stamps_ns`."""
    xyz, distance, intensity, laser, ring, azimuth, return_type, time_ns, packet = (a[:n] for a in buffer)
    packet_time_ns = np.zeros(n_packets, np.int64)
    packet_time_ns[index] = stamps_ns
    return DecodedPoints(model=model, xyz=xyz, distance_m=distance, intensity=intensity, laser_id=laser, ring=ring,
                         azimuth_cdeg=azimuth, return_type=return_type, timestamp_ns=time_ns, packet_index=packet,
                         packet_time_ns=packet_time_ns)


def rotation_starts(azimuth_cdeg: np.ndarray) -> np.ndarray:
    """Indices of the packets (their first firings' azimuths, in order) that begin a new rotation: where the
    azimuth falls by more than half a turn from the packet before."""
    az = np.asarray(azimuth_cdeg, dtype=np.int64)
    return np.flatnonzero(np.diff(az) < -18000) + 1
