"""RoboSense MSOP data packets (1,248 bytes: a header with the UTC time, blocks of one azimuth and its
channels' ranges, big-endian) of the Helios-16P and Ruby-128 decoded a batch at a time (numpy per packet, a
compiled loop per channel): firing azimuth interpolated over each channel's firing time, range, intensity, laser,
ring, per-point time on the sensor's UTC clock and xyz in the sensor frame (x forward, y left, z up). Device-info
(DIFOP) packets and bad packets are counted by reason and skipped. The return mode is not in the MSOP packet (only
in DIFOP): it is configured."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.lidar.compiled_loops import compiled
from drivers.lidar.packet_decoding import (
    RETURN_TYPE_LAST,
    RETURN_TYPE_OTHER,
    RETURN_TYPE_STRONGEST,
    DecodedPoints,
    PacketCheck,
    empty_points,
    filled_points,
    packet_batch,
    points_buffer,
)
from drivers.lidar.robosense_calibration import RobosenseCalibration, load_robosense_calibration

PACKET_SIZE = 1248
MSOP_ID = b"\x55\xaa\x05\x5a"
DIFOP_ID = b"\xa5\xff\x00\x5a\x11\x11\x55\x55"
_ONE_TURN = 36000


@dataclass(frozen=True)
class RobosenseModel:
    name: str
    num_lasers: int
    timestamp_offset: int  # header: 6-byte seconds then 4-byte microseconds of UTC, big-endian
    header_bytes: int
    blocks: int
    block_id: bytes  # each block opens with it; its azimuth (0.01 degrees) follows at byte 2
    channels: int  # per block, 3 bytes each from block byte 4: range, intensity
    distance_resolution_m: float
    lens_offset_m: float  # the receiving lens's distance from the rotation axis (RoboSense's "RX")
    block_s: float  # one block's firing cycle
    firing_s: np.ndarray  # (channels,) time of each channel's firing after its block's
    min_range_m: float
    max_range_m: float


def _helios16p_firing() -> np.ndarray:
    # 16 lasers fire twice a 55.56 us block, one every 1.73 us (RoboSense rs_driver's Helios-16P table):
    # channels 0-15 and then 16-31, laser = channel % 16.
    return np.arange(32) * 1.73e-6


def _ruby128_firing() -> np.ndarray:
    # Lasers fire four at once, 16 groups 3.236 us apart, the second 64 channels with the first
    # (rs_driver's RS128 table).
    return np.tile(np.arange(64) // 4 * 3.236e-6, 2)


HELIOS16P = RobosenseModel("robosense-helios16p", 16, 20, 42, 12, b"\xff\xee", 32, 0.0025, 0.03498, 55.56e-6,
                           _helios16p_firing(), 0.2, 180.0)
RUBY128 = RobosenseModel("robosense-ruby128", 128, 10, 80, 3, b"\xfe", 128, 0.005, 0.03615, 55.55e-6,
                         _ruby128_firing(), 0.4, 250.0)
ROBOSENSE_MODELS = (HELIOS16P.name, RUBY128.name)
_MODELS = {m.name: m for m in (HELIOS16P, RUBY128)}

# Reasons a datagram is skipped, as DecodedPoints.counts and PacketCheck.counts name them.
WRONG_SIZE = "wrong_size"  # not 1,248 bytes
DIFOP = "difop"  # a device-info packet (it belongs on its own port)
BAD_HEADER = "bad_header"  # does not open with the MSOP id
BAD_BLOCK_FLAG = "bad_block_flag"  # a block does not open with the model's block id (another model's packet)
BAD_TIME = "bad_time"  # the microseconds field is 1,000,000 or more
_REASONS = (WRONG_SIZE, DIFOP, BAD_HEADER, BAD_BLOCK_FLAG, BAD_TIME)


def _trig_tables() -> tuple[np.ndarray, np.ndarray]:
    angle = np.radians(np.arange(_ONE_TURN) * 0.01)
    return np.cos(angle).astype(np.float32), np.sin(angle).astype(np.float32)


class RobosenseDecoder:
    """Decodes batches of one sensor's MSOP packets with its angle calibration.

    `dual_return`: the sensor's return mode as its DIFOP packet says. Helios-16P: channels 0-15 are the
    strongest return, 16-31 the second of the same firing (RETURN_TYPE_OTHER, "second strongest" in Nebula's
    decoder). Ruby-128: two blocks of one azimuth are the two returns, a packet's three blocks either AAB or
    ABB (rs_driver); the first of a pair is the strongest, the second the last (Nebula's rule for RoboSense
    dual returns). `rpm` gives the azimuth step of a block with no next firing in its packet to measure it."""

    def __init__(self, model: RobosenseModel, calibration: RobosenseCalibration, dual_return: bool = False,
                 rpm: float = 600.0):
        if calibration.num_lasers != model.num_lasers:
            raise ValueError(f"{calibration.source}: {calibration.num_lasers} lasers, but {model.name} has "
                             f"{model.num_lasers}")
        self._m = model
        self.model = model.name
        self.calibration = calibration
        self.dual_return = dual_return
        channel = np.arange(model.channels)
        self._laser = channel % model.num_lasers
        self._pairs_of_blocks = dual_return and model.channels == model.num_lasers  # Ruby-128
        firing = model.firing_s
        if dual_return and not self._pairs_of_blocks:  # Helios-16P: both halves of a block one firing
            firing = np.tile(firing[: model.num_lasers], model.channels // model.num_lasers)
        self._firing_ns = np.rint(firing * 1e9).astype(np.int64)
        self._azimuth_fraction = (firing / model.block_s).astype(np.float32)
        self._nominal_step = np.float32(round(_ONE_TURN * rpm / 60.0 * model.block_s))
        self._return_type = np.full(model.channels, RETURN_TYPE_STRONGEST, np.uint8)
        if dual_return and not self._pairs_of_blocks:
            self._return_type[16:] = RETURN_TYPE_OTHER
        self._cos, self._sin = _trig_tables()
        elevation = calibration.elevation_cdeg[self._laser] % _ONE_TURN
        self._cos_el, self._sin_el = self._cos[elevation], self._sin[elevation]
        self._az_offset = calibration.azimuth_offset_cdeg[self._laser].astype(np.int32)
        self._ring = calibration.ring[self._laser]

    def check(self, packets: list[bytes]) -> PacketCheck:
        """Which datagrams are this sensor's data packets, their stamps (UTC ns) and first azimuths."""
        counts: dict[str, int] = {}
        batch, index = _as_batch(packets, counts)
        good = self._check_packets(batch, counts)
        accepted = np.zeros(len(packets), bool)
        accepted[index[good]] = True
        time_ns = np.zeros(len(packets), np.int64)
        azimuth = np.zeros(len(packets), np.int32)
        time_ns[index[good]] = self._stamps_ns(batch[good])
        azimuth[index[good]] = _be16(batch[good], self._m.header_bytes + 2).astype(np.int32) % _ONE_TURN
        return PacketCheck(accepted, time_ns, azimuth, {k: v for k, v in counts.items() if v and k != "packets_in"})

    def decode(self, packets: list[bytes]) -> DecodedPoints:
        """The points of a list of datagram payloads of any size, in packet order."""
        counts = {"packets_in": 0, "packets_decoded": 0} | dict.fromkeys(_REASONS, 0)
        batch, index = _as_batch(packets, counts)
        good = self._check_packets(batch, counts)
        if not good.all():
            batch, index = batch[good], index[good]
        counts["packets_decoded"] = int(batch.shape[0])
        if batch.shape[0] == 0:
            return empty_points(counts, None)
        points = self._decode_points(batch, index, counts["packets_in"])
        points.counts = counts
        return points

    def _check_packets(self, batch: np.ndarray, counts: dict[str, int]) -> np.ndarray:
        m = self._m
        difop = np.all(batch[:, : len(DIFOP_ID)] == np.frombuffer(DIFOP_ID, np.uint8), axis=1)
        msop = np.all(batch[:, : len(MSOP_ID)] == np.frombuffer(MSOP_ID, np.uint8), axis=1)
        blocks = self._blocks(batch)
        flags_ok = np.all(blocks[:, :, : len(m.block_id)] == np.frombuffer(m.block_id, np.uint8), axis=(1, 2))
        time_ok = _be32(batch, m.timestamp_offset + 6) < 1_000_000
        counts[DIFOP] = int(difop.sum())
        counts[BAD_HEADER] = int((~difop & ~msop).sum())
        counts[BAD_BLOCK_FLAG] = int((msop & ~flags_ok).sum())
        counts[BAD_TIME] = int((msop & flags_ok & ~time_ok).sum())
        return msop & flags_ok & time_ok

    def _blocks(self, batch: np.ndarray) -> np.ndarray:
        m = self._m
        block_bytes = 4 + 3 * m.channels
        return batch[:, m.header_bytes : m.header_bytes + m.blocks * block_bytes].reshape(-1, m.blocks, block_bytes)

    def _stamps_ns(self, batch: np.ndarray) -> np.ndarray:
        offset = self._m.timestamp_offset
        seconds = np.zeros(batch.shape[0], np.int64)
        for i in range(6):
            seconds = (seconds << 8) | batch[:, offset + i]
        return seconds * 1_000_000_000 + _be32(batch, offset + 6).astype(np.int64) * 1000

    def _block_timing(self, block_azimuth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Per block (n, blocks): the azimuth step over its firing (to the next firing's block; nominal for
        the last or across a gap of over 1 degree in the field of view), its time after the packet's stamp (ns),
        and its return type where blocks, not channels, tell the returns apart (Ruby-128 dual; else None)."""
        f32 = np.float32
        m = self._m
        nominal = self._nominal_step
        block_ns = np.broadcast_to(np.rint(np.arange(m.blocks) * m.block_s * 1e9).astype(np.int64), block_azimuth.shape)
        step = np.full(block_azimuth.shape, nominal, f32)
        if not self._pairs_of_blocks:
            measured = ((block_azimuth[:, 1:] - block_azimuth[:, :-1]) % _ONE_TURN).astype(f32)
            step[:, :-1] = np.where(measured > 100, nominal, measured)
            return step, block_ns, None
        aab = block_azimuth[:, 0] == block_azimuth[:, 1]  # else ABB
        measured = ((block_azimuth[:, 2] - block_azimuth[:, 0]) % _ONE_TURN).astype(f32)
        step[:, 0] = np.where(measured > 100, nominal, measured)
        step[:, 1] = np.where(aab, step[:, 0], nominal)
        second_firing = np.where(aab[:, None], [False, False, True], [False, True, True])
        block_ns = np.where(second_firing, np.int64(round(m.block_s * 1e9)), np.int64(0))
        return_type = np.where(aab[:, None], [RETURN_TYPE_STRONGEST, RETURN_TYPE_LAST, RETURN_TYPE_STRONGEST],
                               [RETURN_TYPE_LAST, RETURN_TYPE_STRONGEST, RETURN_TYPE_LAST]).astype(np.uint8)
        return step, block_ns, return_type

    def _decode_points(self, batch: np.ndarray, index: np.ndarray, n_packets: int) -> DecodedPoints:
        """Per block (azimuth, step, time) with numpy, then every channel in one compiled loop (_decode_channels)."""
        m = self._m
        n = batch.shape[0]
        block_azimuth = _be16(self._blocks(batch), 2).astype(np.int32)  # (n, blocks)
        step, block_ns, block_return_type = self._block_timing(block_azimuth)
        if block_return_type is None:
            block_return_type = np.zeros((n, m.blocks), np.uint8)  # the channel's type (_return_type) is used
        stamps_ns = self._stamps_ns(batch)
        out = points_buffer(n * m.blocks * m.channels)
        kept = _decode_channels(
            batch, index, stamps_ns, m.header_bytes, block_azimuth, step.astype(np.float32),
            np.ascontiguousarray(block_ns), block_return_type, np.float32(m.distance_resolution_m),
            np.float32(m.min_range_m), np.float32(m.max_range_m), np.float32(m.lens_offset_m), self._azimuth_fraction,
            self._az_offset, self._cos_el, self._sin_el, self._cos, self._sin, self._laser.astype(np.uint16),
            self._ring, self._return_type, self._firing_ns, *out)
        return filled_points(m.name, out, kept, n_packets, index, stamps_ns)


@compiled
def _decode_channels(batch, index, stamps_ns, header_bytes, block_azimuth, step, block_ns, block_return_type,
                     resolution, min_range, max_range, lens, azimuth_fraction, azimuth_offset, cos_elevation,
                     sin_elevation, cos_table, sin_table, lasers, rings, channel_return_type, firing_ns, xyz, distance,
                     intensity, laser, ring, azimuth, return_type, time_ns, packet):  # pragma: no cover - compiled
    """The channels with a range within the limits of every packet's blocks into the points_buffer arrays, in
    packet, block, channel order; returns how many. The firing azimuth in whole 0.01 degree steps, the
    interpolation truncated, as RoboSense's SDK does; float32 throughout."""
    n_blocks, n_channels = block_azimuth.shape[1], azimuth_fraction.shape[0]
    block_bytes = 4 + 3 * n_channels
    # Indices unsigned: numba checks each signed index for a negative value, to count it from the end.
    one, two, three = np.uint64(1), np.uint64(2), np.uint64(3)
    k = np.uint64(0)
    for p in range(batch.shape[0]):
        data = batch[p]
        packet_p = index[p]
        for b in range(n_blocks):
            block_at = np.uint64(header_bytes + b * block_bytes + 4)
            block_az, block_step = block_azimuth[p, b], step[p, b]
            block_time = stamps_ns[p] + block_ns[p, b]
            block_type = block_return_type[p, b]
            for c in range(np.uint64(n_channels)):
                at = block_at + three * c
                raw = (np.int64(data[at]) << 8) | data[at + one]
                if raw == 0:
                    continue
                d = np.float32(raw) * resolution
                if d < min_range or d > max_range:
                    continue
                firing = block_az + np.int32(block_step * azimuth_fraction[c])
                final = firing + azimuth_offset[c]
                if final < 0 or final >= 36000:  # mostly not: the remainder only where it changes something
                    final %= 36000
                if firing < 0 or firing >= 36000:
                    firing %= 36000
                xy = d * cos_elevation[c]
                turned, fired = np.uint64(final), np.uint64(firing)  # both in [0, 36000) now
                xyz[k, 0] = xy * cos_table[turned] + lens * cos_table[fired]
                xyz[k, 1] = -(xy * sin_table[turned] + lens * sin_table[fired])
                xyz[k, 2] = d * sin_elevation[c]
                distance[k] = d
                intensity[k] = data[at + two]
                laser[k] = lasers[c]
                ring[k] = rings[c]
                azimuth[k] = firing
                return_type[k] = block_type if block_type else channel_return_type[c]  # the block's, if it has one
                time_ns[k] = block_time + firing_ns[c]
                packet[k] = packet_p
                k += one
    return np.int64(k)


def robosense_decoder(model: str, calibration_path: str | Path | None = None, dual_return: bool = False,
                      rpm: float = 600.0) -> RobosenseDecoder:
    """The decoder of a model named in ROBOSENSE_MODELS with its angle file (None: the model's nominal angles
    are not shipped, so a file is needed); ValueError when the file does not fit the model."""
    if model not in _MODELS:
        raise ValueError(f"unknown RoboSense model {model!r}; known: {', '.join(ROBOSENSE_MODELS)}")
    if calibration_path is None:
        raise ValueError(f"{model}: an angle calibration file is needed (the sensor's DIFOP angles are not read)")
    return RobosenseDecoder(_MODELS[model], load_robosense_calibration(calibration_path), dual_return, rpm)


def _as_batch(packets: list[bytes], counts: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    counts["packets_in"] = len(packets)
    batch, index = packet_batch(packets, (PACKET_SIZE,))
    counts[WRONG_SIZE] = len(packets) - len(index)
    return batch, index


def _be16(a: np.ndarray, offset: int) -> np.ndarray:
    """Big-endian uint16 at byte `offset` of the last axis."""
    return (a[..., offset].astype(np.uint16) << 8) | a[..., offset + 1].astype(np.uint16)


def _be32(a: np.ndarray, offset: int) -> np.ndarray:
    return (_be16(a, offset).astype(np.uint32) << 16) | _be16(a, offset + 2).astype(np.uint32)
