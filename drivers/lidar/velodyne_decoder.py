"""Velodyne data packets (1,206 bytes: 12 blocks of 32 returns, a timestamp, two factory bytes) decoded a batch at a
time (numpy per packet, a compiled loop per return): model and return mode from the factory bytes (HDL-64E:
configured, its upper and lower blocks alternate, dual return seen in its azimuths), azimuth interpolated over each
firing's time, range, intensity, laser id, ring, per-point time and xyz in the sensor frame (x forward, y left,
z up, as velodyne-decoder gives them). Bad packets are counted and skipped."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.lidar.compiled_loops import compiled
from drivers.lidar.packet_decoding import (
    RETURN_TYPE_LAST,
    RETURN_TYPE_STRONGEST,
    DecodedPoints,
    PacketCheck,
    empty_points,
    filled_points,
    packet_batch,
    points_buffer,
)
from drivers.lidar.velodyne_calibration import VelodyneCalibration, load_velodyne_calibration
from drivers.lidar.velodyne_models import (
    BLOCKS_PER_PACKET,
    HDL64E_MODELS,
    MODELS,
    PACKET_SIZE,
    RETURN_DUAL,
    RETURN_LAST,
    RETURN_STRONGEST,
    RETURNS_PER_BLOCK,
    VelodyneModel,
)

_BLOCK_BYTES = 100
_TIMESTAMP_OFFSET = 1200
_RETURN_MODE_OFFSET = 1204
_PRODUCT_ID_OFFSET = 1205

_BANK_FLAGS = np.array([0xEEFF, 0xDDFF, 0xCCFF, 0xBBFF], dtype=np.uint16)  # lasers 0-31, 32-63, ...

_DUAL_ORDER = np.stack(
    [np.arange(BLOCKS_PER_PACKET * RETURNS_PER_BLOCK), np.arange(384).reshape(6, 2, 32).transpose(0, 2, 1).ravel()]
)

def _hdl64e_order() -> np.ndarray:
    # Dual return: firing k's upper bank then its lower, channel by channel the last return (block 4k + 2 + bank)
    # then the strongest (block 4k + bank), as velodyne-decoder gives them.
    firing, bank, channel, last = np.meshgrid(np.arange(3), np.arange(2), np.arange(32), [True, False], indexing="ij")
    block = 4 * firing + bank + 2 * last
    return np.stack([np.arange(384), (block * RETURNS_PER_BLOCK + channel).ravel()])


_HDL64E_ORDER = _hdl64e_order()


_KNOWN_PRODUCT = np.isin(np.arange(256), list(MODELS))  # by factory byte
_KNOWN_MODE = np.isin(np.arange(256), [RETURN_STRONGEST, RETURN_LAST, RETURN_DUAL])

# Reasons a datagram is skipped, as DecodedPoints.counts and PacketCheck.counts name them.
WRONG_SIZE = "wrong_size"  # not 1,206 bytes (position packets are 512)
BAD_BLOCK_FLAG = "bad_block_flag"  # a block's flag is not the bank the model puts there
UNKNOWN_FACTORY = "unknown_factory"  # product id or return mode byte of no model decoded here
FOREIGN_MODEL = "foreign_model"  # a known model, but not the one the calibration is for


def _rotation_tables() -> tuple[np.ndarray, np.ndarray]:
    # As velodyne-decoder caches them: float32 angle of each 0.01 degree step.
    angle = np.float32(0.01) * np.arange(36000, dtype=np.float32) * np.float32(np.pi / 180.0)
    return np.cos(angle), np.sin(angle)


_COS_TABLE, _SIN_TABLE = _rotation_tables()


class VelodyneDecoder:
    """Decodes batches of one sensor's data packets with its calibration.

    VLS-128 packets take their rotation rate from the previous packet's azimuth, so the decoder keeps
    the last packet's azimuth between calls: feed it the packets of one stream in order."""

    def __init__(self, calibration: VelodyneCalibration, min_range_m: float = 0.1, max_range_m: float = 200.0,
                 hdl64e: str | None = None):
        """`hdl64e`: a name of HDL64E_MODELS for an HDL-64E (its packets do not say which it is); otherwise the
        model is the one of the calibration's laser count and the packets' factory bytes."""
        self.calibration = calibration
        self.min_range_m = np.float32(min_range_m)
        self.max_range_m = np.float32(max_range_m)
        if hdl64e is not None:
            if hdl64e not in HDL64E_MODELS or calibration.num_lasers != 64:
                raise ValueError(f"{calibration.source}: {calibration.num_lasers} lasers, not an {hdl64e!r} of "
                                 f"{', '.join(HDL64E_MODELS)}")
            self._model = HDL64E_MODELS[hdl64e]
        else:
            self._model = next((m for m in MODELS.values() if m.num_lasers == calibration.num_lasers), None)
        self._tables = _calibration_tables(self._model, calibration)
        self._prev_azimuth: int | None = None  # VLS-128: first block azimuth of the last packet
        self._prev_rate = np.float32(0.0)

    @property
    def model(self) -> str:
        return self._model.name if self._model is not None else f"Velodyne ({self.calibration.num_lasers} lasers)"

    def check(self, packets: list[bytes]) -> PacketCheck:
        """Which datagrams are this sensor's data packets, their stamps (microseconds past the hour) and the
        azimuth of their first block."""
        counts: dict[str, int] = {}
        batch, index = self._as_batch(packets, counts)
        good, _ = self._check_packets(batch, counts)
        accepted = np.zeros(len(packets), bool)
        accepted[index[good]] = True
        time_ns = np.zeros(len(packets), np.int64)
        azimuth = np.zeros(len(packets), np.int32)
        stamps = batch[good, _TIMESTAMP_OFFSET:_TIMESTAMP_OFFSET + 4].copy().view("<u4")[:, 0]
        time_ns[index[good]] = stamps.astype(np.int64) * 1000
        azimuth[index[good]] = _u16(batch[good], 2).astype(np.int32) % 36000
        return PacketCheck(accepted, time_ns, azimuth, {k: v for k, v in counts.items() if v and k != "packets_in"})

    def decode(self, packets: np.ndarray | list[bytes]) -> DecodedPoints:
        """Decode an (N, 1206) uint8 array or a list of datagram payloads of any size."""
        counts = {"packets_in": 0, "packets_decoded": 0, WRONG_SIZE: 0, BAD_BLOCK_FLAG: 0, UNKNOWN_FACTORY: 0,
                  FOREIGN_MODEL: 0}
        batch, index = self._as_batch(packets, counts)
        good, model = self._check_packets(batch, counts)
        if not good.all():
            batch, index = batch[good], index[good]
        counts["packets_decoded"] = int(batch.shape[0])
        if model is None or batch.shape[0] == 0:
            return empty_points(counts, None if model is None else model.name)
        points = self._decode_points(batch, index, model, counts["packets_in"])
        points.counts = counts
        return points

    @staticmethod
    def _as_batch(packets: np.ndarray | list[bytes], counts: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
        if isinstance(packets, np.ndarray):
            if packets.ndim != 2:
                raise TypeError("expected an (N, packet_size) uint8 array")
            counts["packets_in"] = int(packets.shape[0])
            if packets.shape[1] != PACKET_SIZE:
                counts[WRONG_SIZE] = counts["packets_in"]
                return np.zeros((0, PACKET_SIZE), np.uint8), np.zeros(0, np.int64)
            return packets.astype(np.uint8, copy=False), np.arange(packets.shape[0], dtype=np.int64)
        counts["packets_in"] = len(packets)
        batch, index = packet_batch(packets, (PACKET_SIZE,))
        counts[WRONG_SIZE] = counts["packets_in"] - len(index)
        return batch, index

    def _check_packets(self, batch: np.ndarray, counts: dict[str, int]) -> tuple[np.ndarray, VelodyneModel | None]:
        """Mask of the packets to decode; counts the others by reason."""
        product = batch[:, _PRODUCT_ID_OFFSET]
        mode = batch[:, _RETURN_MODE_OFFSET]
        model = self._model
        flags = _u16(batch[:, :_TIMESTAMP_OFFSET].reshape(-1, BLOCKS_PER_PACKET, _BLOCK_BYTES), 0)
        if model is not None and model.product_id is None:  # HDL-64E: upper and lower blocks alternate
            counts[UNKNOWN_FACTORY] = counts[FOREIGN_MODEL] = 0
            flags_ok = (flags == _BANK_FLAGS[np.arange(BLOCKS_PER_PACKET) % 2]).all(axis=1)
            counts[BAD_BLOCK_FLAG] = int((~flags_ok).sum())
            return flags_ok, model
        known = _KNOWN_PRODUCT[product] & _KNOWN_MODE[mode]
        counts[UNKNOWN_FACTORY] = int((~known).sum())
        mine = known & (product == (model.product_id if model else -1))
        counts[FOREIGN_MODEL] = int((known & ~mine).sum())
        if model is not None and model.num_lasers == 128:
            blocks_used = np.where(mode == RETURN_DUAL, 8, 12)
            bank = np.arange(BLOCKS_PER_PACKET) // np.where(mode == RETURN_DUAL, 2, 1)[:, None] % 4
            ok = (flags == _BANK_FLAGS[bank]) | (np.arange(BLOCKS_PER_PACKET)[None, :] >= blocks_used[:, None])
        else:
            ok = flags == _BANK_FLAGS[0]
        flags_ok = ok.all(axis=1)
        counts[BAD_BLOCK_FLAG] = int((mine & ~flags_ok).sum())
        return mine & flags_ok, model

    def _vls128_rate(self, first_azimuth: np.ndarray, packet_duration: np.ndarray) -> np.ndarray:
        """Azimuth units per second of each packet, from the previous packet (velodyne-decoder's rule:
        a rate above 1.8x the last accepted one means a dropped packet and keeps the last one)."""
        az = first_azimuth.astype(np.int64)
        prev = np.concatenate([[-1 if self._prev_azimuth is None else self._prev_azimuth], az[:-1]])
        rate = ((az - prev + 36000) % 36000).astype(np.float32) / packet_duration
        rate[prev < 0] = 0.0
        self._prev_rate = np.float32(_keep_plausible_rates(rate, prev >= 0, self._prev_rate))  # numba gives a float
        self._prev_azimuth = int(az[-1])
        return rate

    def _decode_points(self, batch: np.ndarray, index: np.ndarray, model: VelodyneModel,
                       n_packets: int) -> DecodedPoints:
        """What is per packet (azimuths, modes, rotation rates) with numpy, then every return in one compiled loop
        (_decode_returns) in velodyne-decoder's order: block by block, a dual pair channel by channel (last,
        strongest); what depends on the laser and firing only comes from per-slot tables."""
        n = batch.shape[0]
        f32 = np.float32
        block_azimuth = _u16(batch[:, :_TIMESTAMP_OFFSET].reshape(n, BLOCKS_PER_PACKET, _BLOCK_BYTES), 2)  # (n, 12)
        timestamp_us = batch[:, _TIMESTAMP_OFFSET : _TIMESTAMP_OFFSET + 4].copy().view("<u4")[:, 0]
        mode = batch[:, _RETURN_MODE_OFFSET]
        hdl64e = model.product_id is None
        # The HDL-64E has no return mode byte: a dual-return packet repeats its first firing's azimuth in block 2.
        dual = block_azimuth[:, 0] == block_azimuth[:, 2] if hdl64e else mode == RETURN_DUAL
        last_mode = np.zeros(n, bool) if hdl64e else mode == RETURN_LAST
        if model.num_lasers == 128:
            seq = model.firing_time_s[4, 0] - model.firing_time_s[0, 0]
            rate = self._vls128_rate(block_azimuth[:, 0], np.where(dual, seq, f32(3) * seq).astype(f32))
        else:
            last_row = np.where(dual, (BLOCKS_PER_PACKET - 1) // 2, BLOCKS_PER_PACKET - 1)
            duration = model.firing_time_s[last_row, 0] - model.firing_time_s[0, 0]
            diff = (block_azimuth[:, -1].astype(np.int32) - block_azimuth[:, 0] + 36000) % 36000
            rate = diff.astype(f32) / duration
        tables, t, cal = self._tables, self._tables.slots, self.calibration
        out = points_buffer(n * BLOCKS_PER_PACKET * RETURNS_PER_BLOCK)
        stamps_us = timestamp_us.astype(np.int64)
        kept = _decode_returns(
            batch, index, stamps_us, block_azimuth, dual, last_mode, rate.astype(f32, copy=False),
            t["slots"], t["at"], t["partner_at"], t["keeper"], t["own_type"], t["block"], t["laser"], t["dt"],
            t["time_ns"], t["dist_correction"], t["angles"], f32(cal.distance_resolution_m), self.min_range_m,
            self.max_range_m, _COS_TABLE, _SIN_TABLE, tables.lasers, cal.ring, tables.has_offsets,
            tables.two_point, tables.intensity_rule, *out)
        return filled_points(model.name, out, kept, n_packets, index, stamps_us * 1000)


@dataclass(frozen=True)
class _CalibrationTables:
    """What _decode_returns takes from a model and calibration, made once (_calibration_tables)."""

    slots: dict[str, np.ndarray]  # _slot_tables; empty without a model
    lasers: np.ndarray  # _laser_tables
    has_offsets: bool  # with no offsets the offset terms vanish: the formula velodyne-decoder uses for such files
    two_point: bool  # the calibration's two_point_correction
    intensity_rule: int  # INTENSITY_RAW, INTENSITY_CLIPPED or INTENSITY_FOCAL (see _decode_returns)


_TABLES_KEPT = 8  # calibrations whose tables are kept for the next decoder made with the same
_tables_made: dict[tuple, _CalibrationTables] = {}


def _calibration_tables(model: VelodyneModel | None, calibration: VelodyneCalibration) -> _CalibrationTables:
    """The tables of a model and calibration: the ones made for a decoder before when the calibration's per-laser
    values are the same (a decoder made anew for every stream of one sensor makes them once), otherwise new ones."""
    cal = calibration
    per_laser = (cal.rot_correction_rad, cal.vert_correction_rad, cal.dist_correction_m, cal.dist_correction_x_m,
                 cal.dist_correction_y_m, cal.vert_offset_m, cal.horiz_offset_m, cal.focal_distance, cal.focal_slope,
                 cal.min_intensity, cal.max_intensity)
    key = (None if model is None else model.name, cal.num_lasers,
           b"".join(np.asarray(a, np.float64).tobytes() for a in per_laser))
    tables = _tables_made.get(key)
    if tables is None:
        two_point = cal.two_point_correction
        if np.any(cal.focal_slope != 0):
            rule = INTENSITY_FOCAL
        elif np.all(cal.min_intensity <= 0) and np.all(cal.max_intensity >= 255):
            rule = INTENSITY_RAW  # a raw byte is always within the limits
        else:
            rule = INTENSITY_CLIPPED
        tables = _CalibrationTables(
            slots=_slot_tables(model, cal) if model is not None else {}, lasers=_laser_tables(cal),
            has_offsets=bool(np.any(cal.vert_offset_m) or np.any(cal.horiz_offset_m)) or two_point,
            two_point=two_point, intensity_rule=rule)
        if len(_tables_made) >= _TABLES_KEPT:
            del _tables_made[next(iter(_tables_made))]
        _tables_made[key] = tables
    return tables


# How a return's intensity is made from its raw byte: as it is; clipped to the laser's limits; velodyne-decoder's
# focal correction (focal_slope) and then clipped.
INTENSITY_RAW, INTENSITY_CLIPPED, INTENSITY_FOCAL = 0, 1, 2
# Rows of the (LASER_TABLE_ROWS, L) float32 per-laser table _decode_returns takes.
(_COS_ROT, _SIN_ROT, _COS_VERT, _SIN_VERT, _VERT_OFFSET, _HORIZ_OFFSET, _DIST_CORRECTION, _DIST_CORRECTION_X,
 _DIST_CORRECTION_Y, _FOCAL_SLOPE, _FOCAL_DISTANCE, _MIN_INTENSITY, _MAX_INTENSITY) = range(13)
LASER_TABLE_ROWS = 13


def _laser_tables(calibration: VelodyneCalibration) -> np.ndarray:
    """(LASER_TABLE_ROWS, L) float32: the calibration's per-laser values and the cosines and sines of its angles."""
    f32 = np.float32
    rot, vert = calibration.rot_correction_rad.astype(f32), calibration.vert_correction_rad.astype(f32)
    rows = (np.cos(rot), np.sin(rot), np.cos(vert), np.sin(vert), calibration.vert_offset_m,
            calibration.horiz_offset_m, calibration.dist_correction_m, calibration.dist_correction_x_m,
            calibration.dist_correction_y_m, calibration.focal_slope, calibration.focal_distance,
            calibration.min_intensity, calibration.max_intensity)
    return np.stack([np.asarray(r).astype(f32) for r in rows])


@compiled
def _keep_plausible_rates(rate, measured, accepted):  # pragma: no cover - compiled
    """VLS-128: each measured rate above 1.8x the last accepted one replaced by it (a packet was dropped); returns
    the last accepted rate. Sequential by nature."""
    limit = np.float32(1.8)
    for i in range(rate.shape[0]):
        if not measured[i]:
            continue
        if accepted > 0 and rate[i] > accepted * limit:
            rate[i] = accepted
        else:
            accepted = rate[i]
    return accepted


@compiled
def _decode_returns(batch, index, timestamp_us, block_azimuth, dual, last_mode, rate, slots, slot_at, partner_at,
                    keeper, own_type, slot_block, slot_laser, slot_dt, slot_time_ns, slot_dist_correction, slot_angles,
                    resolution, min_range, max_range, cos_table, sin_table, lasers, rings, has_offsets, two_point,
                    intensity_rule, xyz, distance, intensity, laser, ring, azimuth, return_type, time_ns,
                    packet):  # pragma: no cover - compiled
    """The kept returns of every packet into the points_buffer arrays, in slot order; returns how many. Float32
    throughout, the operations in velodyne-decoder's order. Each packet walks the `slots` in use of its row of the
    slot tables (_slot_tables: 0 single, 1 dual return). A return is kept with a nonzero range within the limits
    and a return type: of a dual pair of equal returns, the keeper's carries both types and its partner's none."""
    f32 = np.float32
    both = RETURN_TYPE_LAST | RETURN_TYPE_STRONGEST
    near_limit, x_start, y_start = f32(25.04), f32(2.4), f32(1.93)
    x_span, y_span = f32(25.04 - 2.4), f32(25.04 - 1.93)
    half, turn_round = f32(0.5), f32(36000.5)
    # Indices unsigned (the slot tables' too): numba checks each signed index for a negative value, to count it
    # from the end; 1.4x on this loop.
    one, two, turn = np.uint64(1), np.uint64(2), np.uint64(36000)
    k = np.uint64(0)
    for p in range(batch.shape[0]):
        is_dual = dual[p]
        row = 1 if is_dual else 0
        single_type = RETURN_TYPE_LAST if last_mode[p] else RETURN_TYPE_STRONGEST
        stamp_ns, rate_p, packet_p = timestamp_us[p] * 1000, rate[p], index[p]
        data, azimuth_p = batch[p], block_azimuth[p]
        at_r, partner_r, keeper_r, own_r = slot_at[row], partner_at[row], keeper[row], own_type[row]
        block_r, laser_r, dt_r, time_r = slot_block[row], slot_laser[row], slot_dt[row], slot_time_ns[row]
        correction_r, angles_r = slot_dist_correction[row], slot_angles[row]
        for j in range(np.uint64(slots[row])):
            at = at_r[j]
            raw_distance = np.int64(data[at]) | (np.int64(data[at + one]) << 8)
            if raw_distance == 0:
                continue
            kind = single_type
            if is_dual:
                other = partner_r[j]
                same = (data[at] == data[other] and data[at + one] == data[other + one]
                        and data[at + two] == data[other + two])
                kind = (both if keeper_r[j] else 0) if same else own_r[j]
                if kind == 0:
                    continue
            d = f32(raw_distance) * resolution
            d += correction_r[j]
            if d < min_range or d > max_range:
                continue
            az_f = f32(azimuth_p[block_r[j]]) + rate_p * dt_r[j]
            az_f += turn_round
            az = np.uint64(az_f) % turn  # az_f > 0: truncation is the floor
            n = laser_r[j]
            cos_az, sin_az = cos_table[az], sin_table[az]
            cos_rc, sin_rc = angles_r[j, _COS_ROT], angles_r[j, _SIN_ROT]
            cos_rot = cos_az * cos_rc + sin_az * sin_rc  # cos(azimuth - rot_correction)
            sin_rot = sin_az * cos_rc - cos_az * sin_rc
            cos_v, sin_v = angles_r[j, _COS_VERT], angles_r[j, _SIN_VERT]
            if not has_offsets:
                xy = d * cos_v
                xyz[k, 0] = xy * cos_rot
                xyz[k, 1] = -(xy * sin_rot)
                xyz[k, 2] = d * sin_v
            else:
                v_off, h_off = lasers[_VERT_OFFSET, n], lasers[_HORIZ_OFFSET, n]
                d_x, d_y = d, d
                if two_point and f32(raw_distance) * resolution < near_limit:
                    # HDL-64E's distance-dependent corrections along x and y: linear in |x| and |y| (from 2.4 and
                    # 1.93 m to 25.04 m) for returns whose raw range is under 25.04 m, as velodyne-decoder 3.1.0
                    dc, dcx, dcy = lasers[_DIST_CORRECTION, n], lasers[_DIST_CORRECTION_X, n], lasers[
                        _DIST_CORRECTION_Y, n]
                    xy = d * cos_v
                    xx = abs(xy * sin_rot - h_off * cos_rot)
                    yy = abs(xy * cos_rot + h_off * sin_rot)
                    d_x = d + ((dc - dcx) * (xx - x_start) / x_span + dcx - dc)
                    d_y = d + ((dc - dcy) * (yy - y_start) / y_span + dcy - dc)
                # As velodyne-decoder 3.1.0 computes it (found by probing it; ROS velodyne_pointcloud differs): the
                # offsets are not turned by the laser's elevation, z takes the mean of the x and y distances.
                xy_x = d_x * cos_v
                xy_y = d_y * cos_v
                xyz[k, 0] = xy_y * cos_rot + h_off * sin_rot
                xyz[k, 1] = -(xy_x * sin_rot - h_off * cos_rot)
                xyz[k, 2] = (d_x + d_y) * half * sin_v + v_off
            value = f32(data[at + two])
            if intensity_rule == INTENSITY_FOCAL:
                # As velodyne-decoder computes it: the file's focal_distance times 100 (ROS velodyne_pointcloud
                # takes the value as it is; the two disagree, velodyne-decoder is the oracle checked here).
                focal_offset = f32(1) - lasers[_FOCAL_DISTANCE, n] * f32(100) / f32(13100)
                falloff = f32(1) - f32(raw_distance) / f32(65535)
                value = value + f32(256) * lasers[_FOCAL_SLOPE, n] * abs(focal_offset * focal_offset -
                                                                         falloff * falloff)
            if intensity_rule != INTENSITY_RAW:
                value = min(max(value, lasers[_MIN_INTENSITY, n]), lasers[_MAX_INTENSITY, n])
            distance[k] = d
            intensity[k] = value
            laser[k] = n
            ring[k] = rings[n]
            azimuth[k] = az
            return_type[k] = kind
            time_ns[k] = stamp_ns + time_r[j]
            packet[k] = packet_p
            k += one
    return np.int64(k)


def _slot_tables(model: VelodyneModel, calibration: VelodyneCalibration) -> dict[str, np.ndarray]:
    """Per return slot in use (velodyne-decoder's order; see VelodyneDecoder._decode_points), for single (row 0) and
    dual return (row 1) packets, made once per calibration: `slots` (2,) how many a row has, and per slot its
    return's byte offset, its dual partner's (the other return of the same firing) and whether it is the keeper of
    an equal pair (dual blocks 2k: the last returns, 2k + 1 the strongest; HDL-64E 4k, 4k + 1 the strongest,
    4k + 2, 4k + 3 the last) and its own type, its block, laser, the time since its block's reference firing
    (azimuth interpolation), its firing time, the laser's distance correction and angles (_COS_ROT.._SIN_VERT)."""
    order = _DUAL_ORDER if model.product_id is not None else _HDL64E_ORDER  # (2, 384) block * 32 + channel
    block, channel = order // RETURNS_PER_BLOCK, order % RETURNS_PER_BLOCK
    dual = np.array([[False], [True]])
    timing = model.firing_time_s
    row = np.where(dual, block // 2, block)  # dual: two blocks (last, strongest) share one firing
    if model.product_id is None:  # HDL-64E: upper (even) and lower (odd) blocks of one firing
        laser = 32 * (block % 2) + channel
        row = np.where(dual, block // 4 * 2 + block % 2, block)
        t0 = timing[np.where(dual, block // 4 * 2, block // 2 * 2), 0]
        in_use = np.ones_like(block, dtype=bool)
        keeper = block % 4 < 2
        partner = np.where(keeper, block + 2, block - 2)
        own_type = np.where(keeper, RETURN_TYPE_STRONGEST, RETURN_TYPE_LAST)
    else:
        if model.num_lasers == 128:
            bank = np.where(dual, block // 2, block) % 4
            laser = 32 * bank + channel
            t0 = timing[np.where(dual, 0, block // 4 * 4), 0]
            in_use = ~dual | (block < 8)  # dual return: blocks 8-11 are empty
        else:
            laser = channel % model.num_lasers
            t0 = timing[row, 0]
            in_use = np.ones_like(block, dtype=bool)
        keeper = block % 2 == 0
        partner = block ^ 1
        own_type = np.where(keeper, RETURN_TYPE_LAST, RETURN_TYPE_STRONGEST)
    time = timing[row, channel]
    in_use = np.broadcast_to(in_use, block.shape)
    angles = _laser_tables(calibration)[[_COS_ROT, _SIN_ROT, _COS_VERT, _SIN_VERT]].T[laser]  # (2, 384, 4)
    per_slot = {
        "at": (block * _BLOCK_BYTES + 4 + channel * 3).astype(np.uint64),
        "partner_at": (partner * _BLOCK_BYTES + 4 + channel * 3).astype(np.uint64),
        "keeper": keeper,
        "own_type": own_type.astype(np.uint8),
        "block": block.astype(np.uint64),
        "laser": laser.astype(np.uint64),
        "dt": (time - t0).astype(np.float32),
        "time_ns": np.rint(time.astype(np.float64) * 1e9).astype(np.int64),
        "dist_correction": calibration.dist_correction_m.astype(np.float32)[laser],
        "angles": angles,
    }
    tables = {"slots": in_use.sum(axis=1)}
    for name, values in per_slot.items():  # the slots in use first in each row, in order
        values = np.broadcast_to(values, block.shape + values.shape[2:])
        packed = np.zeros_like(values)
        for r in range(2):
            packed[r, : tables["slots"][r]] = values[r][in_use[r]]
        tables[name] = np.ascontiguousarray(packed)
    return tables


def _u16(a: np.ndarray, offset: int) -> np.ndarray:
    """Little-endian uint16 at byte `offset` of the last axis."""
    return a[..., offset].astype(np.uint16) | (a[..., offset + 1].astype(np.uint16) << 8)


VELODYNE_MODELS = ("velodyne-vlp16", "velodyne-vlp32c", "velodyne-vls128", "velodyne-hdl64e")
_MODEL_LASERS = dict(zip(VELODYNE_MODELS, (16, 32, 128, 64), strict=True))


def velodyne_decoder(model: str, calibration_path: str | Path, hdl64e: str = "HDL-64E S3") -> VelodyneDecoder:
    """The decoder of a model named in VELODYNE_MODELS with its calibration YAML; ValueError when the file's
    laser count does not fit the model. `hdl64e`: which HDL-64E of HDL64E_MODELS (its packets do not say;
    velodyne-decoder's hdl64e.py tells S2 from S3 only from the whole calibration block that the status bytes
    spell out over some thousand packets)."""
    if model not in _MODEL_LASERS:
        raise ValueError(f"unknown Velodyne model {model!r}; known: {', '.join(VELODYNE_MODELS)}")
    calibration = load_velodyne_calibration(calibration_path)
    if calibration.num_lasers != _MODEL_LASERS[model]:
        raise ValueError(f"{calibration.source}: {calibration.num_lasers} lasers, but {model} has "
                         f"{_MODEL_LASERS[model]}")
    return VelodyneDecoder(calibration, hdl64e=hdl64e if model == "velodyne-hdl64e" else None)
