"""Hesai data packets (Pandar40P, Pandar64, PandarQT128, PandarXT32, Pandar128E4X/OT128, PandarAT128) decoded a
batch at a time (numpy per packet, a compiled loop per return): returns per firing from the tail's return mode,
range, reflectivity, channel, ring, per-point firing time on the sensor's UTC clock and xyz in the sensor frame
(x forward, y left, z up). Foreign, truncated and malformed datagrams are counted per reason and skipped.
`hesai_decoder(model, path)` builds one from the model's angle table; `hesai_imu_samples` reads the IMU fields the
128E4X tail carries."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivers.lidar.compiled_loops import compiled
from drivers.lidar.hesai_calibration import (
    AT128_ADJUST_ENTRIES,
    AT128_ADJUST_STEP_UNITS,
    AT128_ANGLE_UNITS_PER_DEG,
    AT128Correction,
    HesaiAngles,
    load_at128_correction,
    load_hesai_angles,
)
from drivers.lidar.hesai_packet_formats import (
    FORMATS,
    HESAI_MODELS,
    N_RETURNS,
    HesaiFormat,
    format_of,
    packet_times_ns,
    return_type_table,
    u16,
)
from drivers.lidar.packet_decoding import (
    DecodedPoints,
    PacketCheck,
    empty_points,
    filled_points,
    packet_batch,
    points_buffer,
)

__all__ = ["HESAI_MODELS", "HesaiDecoder", "hesai_decoder", "hesai_imu_samples"]

# Reasons a datagram is skipped, as DecodedPoints.counts and PacketCheck.counts name them.
WRONG_SIZE = "wrong_size"  # no Hesai data packet size of this model (or truncated)
FOREIGN_MODEL = "foreign_model"  # another Hesai model's data packet
BAD_HEADER = "bad_header"  # the model's size, but not its header (signature, laser and block counts, distance unit)
BAD_BLOCK_FLAG = "bad_block_flag"  # a block's start flag is wrong (Pandar40P)
UNKNOWN_RETURN_MODE = "unknown_return_mode"  # a return mode byte of no mode, or not fitting the blocks
BAD_TIMESTAMP = "bad_timestamp"  # the tail's date or microseconds are out of range
REASONS = (WRONG_SIZE, FOREIGN_MODEL, BAD_HEADER, BAD_BLOCK_FLAG, UNKNOWN_RETURN_MODE, BAD_TIMESTAMP)

_AT128_TURN = 360 * AT128_ANGLE_UNITS_PER_DEG
_COS_ELEVATION, _SIN_ELEVATION, _COS_OFFSET, _SIN_OFFSET = range(4)  # rows of HesaiDecoder._pandar_angles
_COS_CDEG = np.cos(np.deg2rad(np.arange(36000) * 0.01)).astype(np.float32)
_SIN_CDEG = np.sin(np.deg2rad(np.arange(36000) * 0.01)).astype(np.float32)
# AT128: the cosine and sine of an azimuth in its units (0.01 / 256 degree) from two float64 tables by the angle sum
# formulas, coarse steps of _AT128_FINE_STEPS units and the fine ones within (np.cos and np.sin per point were 1.5x
# the loop's time; the xyz they give differ from those in the last float32 bit at most, in 118 of 1.4 M values of
# bench/lidar.py's AT128 packets, by under 1e-13 m: those near 0).
_AT128_FINE_STEPS = np.uint64(4096)
_AT128_UNIT_RAD = np.pi / (180 * AT128_ANGLE_UNITS_PER_DEG)
_coarse_rad = np.arange(_AT128_TURN // 4096 + 1) * 4096 * _AT128_UNIT_RAD
_AT128_COS_COARSE, _AT128_SIN_COARSE = np.cos(_coarse_rad), np.sin(_coarse_rad)
_AT128_COS_FINE, _AT128_SIN_FINE = np.cos(np.arange(4096) * _AT128_UNIT_RAD), np.sin(np.arange(4096) * _AT128_UNIT_RAD)


class HesaiDecoder:
    """Decodes batches of one sensor's data packets with its angle table (AT128: its correction file).

    A dual (multiple) return firing gives one point per distinct return, as nebula does: of returns with the
    same distance and reflectivity, or within `dual_return_distance_threshold_m` of another, only the last
    block's is kept; a kept point carries the return type bits of every return it stands for."""

    def __init__(self, fmt: HesaiFormat, angles: HesaiAngles | AT128Correction, min_range_m: float = 0.3,
                 max_range_m: float = 300.0, dual_return_distance_threshold_m: float = 0.1):
        self.format = fmt
        self.angles = angles
        self.min_range_m = max(min_range_m, fmt.min_range_m)
        self.max_range_m = min(max_range_m, fmt.max_range_m)
        self.dual_threshold_m = dual_return_distance_threshold_m
        channels = fmt.n_channels
        # _decode_units' angles: the one kind the table is, the other's arrays empty
        self._pandar_angles = np.zeros((4, channels), np.float32)
        self._at128_angles = (np.zeros(channels, np.int64), np.zeros(channels, np.int64),
                              np.zeros((channels, AT128_ADJUST_ENTRIES), np.int64),
                              np.zeros((channels, AT128_ADJUST_ENTRIES), np.int64))
        if isinstance(angles, HesaiAngles):  # per-channel cosines and sines, float32
            elevation, offset = np.deg2rad(angles.elevation_deg), np.deg2rad(angles.azimuth_offset_deg)
            self._pandar_angles = np.stack([np.cos(elevation), np.sin(elevation), np.cos(offset),
                                            np.sin(offset)]).astype(np.float32)
        else:
            self._at128_angles = tuple(np.ascontiguousarray(a, dtype=np.int64) for a in (
                angles.azimuth, angles.elevation, angles.azimuth_adjust, angles.elevation_adjust))
        self._types = return_type_table(fmt.first_last_reversed)
        # By the header's distance unit byte (4 mm where the model has none): the unit in metres, the raw range
        # bounds and the dual-return threshold in raw units (byte 0 is a bad header: never looked up)
        units = np.arange(256) * 1e-3 if fmt.dis_unit_at is not None else np.full(256, 0.004)
        units[0] = 0.004 if fmt.dis_unit_at is None else 1e-3
        self._units_m = units
        self._lo, self._hi = _raw_bounds(units, self.min_range_m, self.max_range_m)
        self._near = _raw_below(units, self.dual_threshold_m)

    @property
    def model(self) -> str:
        return self.format.model

    def check(self, packets: list[bytes]) -> PacketCheck:
        """Which datagrams are this sensor's data packets, their UTC stamps and their first block's azimuth."""
        counts: dict[str, int] = {}
        batch, index, stamps_ns = self._accepted(packets, counts)
        accepted = np.zeros(len(packets), bool)
        accepted[index] = True
        time_ns = np.zeros(len(packets), np.int64)
        azimuth = np.zeros(len(packets), np.int32)
        time_ns[index] = stamps_ns
        azimuth[index] = self._firing_azimuth(self._block_azimuth(batch)[:, :1])[:, 0]
        return PacketCheck(accepted, time_ns, azimuth, {k: v for k, v in counts.items() if v})

    def decode(self, packets: list[bytes]) -> DecodedPoints:
        counts = {"packets_in": len(packets), "packets_decoded": 0} | dict.fromkeys(REASONS, 0)
        batch, index, stamps_ns = self._accepted(packets, counts)
        counts["packets_decoded"] = len(index)
        if len(index) == 0:
            return empty_points(counts, self.model)
        points = self._decode_points(batch, index, stamps_ns, len(packets))
        points.counts = counts
        return points

    def _accepted(self, packets: list[bytes], counts: dict[str, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model's good packets as an (n, width) uint8 array (packet_batch: the optional trailing fields cut off
        unless every packet has them), their positions in `packets` and their UTC stamps; the others counted by
        reason."""
        fmt = self.format
        batch, index = packet_batch(packets, fmt.sizes)
        if len(index) < len(packets):
            for i in set(range(len(packets))).difference(index.tolist()):
                other = format_of(packets[i])
                reason = FOREIGN_MODEL if other is not None and other is not fmt else WRONG_SIZE
                counts[reason] = counts.get(reason, 0) + 1
        header_ok = np.ones(len(batch), bool)
        for at, value in fmt.header:
            header_ok &= batch[:, at] == value
        if fmt.dis_unit_at is not None:
            header_ok &= batch[:, fmt.dis_unit_at] != 0
        checks = [(BAD_HEADER, header_ok)]
        if fmt.block_flag:
            starts = fmt.first_block + fmt.block_size * np.arange(fmt.n_blocks)
            flag = np.frombuffer(fmt.block_flag, np.uint8)
            checks.append((BAD_BLOCK_FLAG, np.all(batch[:, starts[:, None] + np.arange(2)] == flag, axis=(1, 2))))
        mode = batch[:, fmt.return_mode_at]
        n_returns = N_RETURNS[mode]
        checks.append((UNKNOWN_RETURN_MODE, (n_returns > 0) & (fmt.n_blocks % np.maximum(n_returns, 1) == 0)))
        stamps_ns, stamp_ok = packet_times_ns(fmt, batch)
        checks.append((BAD_TIMESTAMP, stamp_ok))
        good = np.ones(len(batch), bool)
        for reason, ok in checks:
            counts[reason] = counts.get(reason, 0) + int((good & ~ok).sum())
            good &= ok
        return (batch, index, stamps_ns) if good.all() else (batch[good], index[good], stamps_ns[good])

    def _block_azimuth(self, batch: np.ndarray) -> np.ndarray:
        """(n, blocks) raw azimuth: 0.01 degree, AT128 0.01/256 degree of the motor."""
        fmt = self.format
        blocks = batch[:, fmt.first_block : fmt.first_block + fmt.n_blocks * fmt.block_size]
        blocks = blocks.reshape(len(batch), fmt.n_blocks, fmt.block_size)
        azimuth = u16(blocks, fmt.azimuth_at)
        if fmt.fine_azimuth:
            azimuth = (azimuth << 8) + blocks[:, :, fmt.azimuth_at + 2]
        return azimuth

    def _at128_field(self, raw_azimuth: np.ndarray) -> np.ndarray:
        """Index of the mirror whose frame the raw motor azimuth lies in (frames in ascending start order)."""
        start = self.angles.frame_start
        return (np.searchsorted(start, raw_azimuth, side="right") - 1) % len(start)

    def _firing_azimuth(self, raw_azimuth: np.ndarray) -> np.ndarray:
        """0.01 degree azimuth of a firing before per-channel offsets: the block's azimuth; AT128: twice the motor
        angle past its mirror's frame start (it rises across one frame and wraps at the next)."""
        if not self.format.fine_azimuth:
            return (raw_azimuth % 36000).astype(np.int32)
        start = self.angles.frame_start[self._at128_field(raw_azimuth)]
        doubled = ((raw_azimuth - start) % _AT128_TURN) * 2 % _AT128_TURN
        return (doubled // 256).astype(np.int32)

    def _decode_points(self, batch: np.ndarray, index: np.ndarray, stamps_ns: np.ndarray,
                       n_packets: int) -> DecodedPoints:
        """What is per packet and block (stamps, range bounds, azimuths, firing tables) with numpy, then every unit in
        one compiled loop (_decode_units) in nebula's order: packet, firing, channel, return."""
        fmt = self.format
        n = len(batch)
        unit_byte = np.zeros(n, np.uint8) if fmt.dis_unit_at is None else batch[:, fmt.dis_unit_at]
        dis_unit, lo, hi, near_raw = self._units_m[unit_byte], self._lo[unit_byte], self._hi[unit_byte], self._near[
            unit_byte]
        mode = batch[:, fmt.return_mode_at]
        n_returns = N_RETURNS[mode]
        raw_azimuth = self._block_azimuth(batch)
        frame_start = (self.angles.frame_start[self._at128_field(raw_azimuth)] if fmt.fine_azimuth
                       else np.zeros_like(raw_azimuth))
        firing = fmt.firing
        out = points_buffer(n * fmt.n_blocks * fmt.n_channels)
        kept = _decode_units(
            batch, index, stamps_ns, fmt.first_block + fmt.first_unit, fmt.block_size,
            fmt.unit_size, fmt.n_channels, n_returns, mode, lo, hi, near_raw,
            dis_unit, raw_azimuth, self._firing_azimuth(raw_azimuth), frame_start, firing.block_ns(fmt.n_blocks),
            firing.channel_ns, firing.rows(n_returns, batch, fmt.n_blocks), self._types, fmt.fine_azimuth,
            self._pandar_angles, *self._at128_angles, self.angles.ring, *out)
        return filled_points(self.model, out, kept, n_packets, index, stamps_ns)


@compiled
def _decode_units(batch, index, stamps_ns, first_unit, block_size, unit_size, n_channels, n_returns, mode, lo, hi,
                  near_raw, dis_unit, raw_azimuth, firing_azimuth, frame_start, block_ns, channel_ns, table_rows,
                  types, at128, pandar_angles, at128_azimuth, at128_elevation, at128_azimuth_adjust,
                  at128_elevation_adjust, rings, xyz, distance, intensity, laser, ring, azimuth, return_type, time_ns,
                  packet):  # pragma: no cover - compiled
    """The kept returns of every packet into the points_buffer arrays; returns how many. A return is kept with a raw
    range within the packet's bounds [lo, hi] (the metre limits in its unit); of a multiple-return firing's returns,
    one equal to another (distance and reflectivity) or within near_raw of it is dropped unless it is the firing's
    last, which then carries its type bits too (nebula keeps only the last). Pandar: the block azimuth's cosine and
    sine from a 0.01 degree table, the channel's offset added by the angle sum formulas, float32. AT128 (float64,
    then float32): the azimuth twice the motor angle past the mirror's frame start, less the channel's azimuth,
    plus the adjustment the file gives every 2 degrees of motor angle, interpolated (nebula's rule; past the last
    entry the last one is taken; its cosine and sine from _AT128_COS_COARSE.. tables), the elevation the channel's
    plus its adjustment. Hesai's azimuth runs clockwise
    seen from above, 0 forward. What depends on the firing only is worked out once per firing, the direction of a
    channel once per firing and channel (AT128: an elevation's cosine and sine kept per channel until it changes)."""
    f32 = np.float32
    units_d = np.empty(3, np.int64)
    units_refl = np.empty(3, np.int64)
    dropped = np.zeros(3, np.bool_)
    keep = np.zeros(3, np.bool_)
    kinds = np.zeros(3, np.uint8)
    angle_unit = np.pi / (180 * AT128_ANGLE_UNITS_PER_DEG)
    hundredth = AT128_ANGLE_UNITS_PER_DEG // 100
    last_entry = AT128_ADJUST_ENTRIES - 1
    elevation_seen = np.full(n_channels, np.nan)  # AT128: the elevation (angle units) of the cosine and sine kept
    cos_elevation_seen = np.zeros(n_channels)
    sin_elevation_seen = np.zeros(n_channels)
    cos_b = sin_b = f32(0)
    step = upper = turned = 0
    part = 0.0
    # Indices unsigned where it counts: numba checks each signed index for a negative value, to count it from
    # the end.
    one, two = np.uint64(1), np.uint64(2)
    unit_step, block_step = np.uint64(unit_size), np.uint64(block_size)
    dir_x = dir_y = f32(0)  # Pandar: the channel's horizontal direction in this firing
    cos_el = sin_el = cos_az = sin_az = 0.0  # AT128
    k = np.uint64(0)
    for p in range(batch.shape[0]):
        nr = n_returns[p]
        data = batch[p]
        lo_p, hi_p, near_p, unit_p, mode_p = lo[p], hi[p], near_raw[p], dis_unit[p], mode[p]
        stamp_p, packet_p = stamps_ns[p], index[p]
        single_type = types[mode_p, 0, 1]
        for f in range(raw_azimuth.shape[1] // nr):
            first = f * nr  # the firing's first block: its azimuth
            raw = raw_azimuth[p, first]
            firing_az = firing_azimuth[p, first]
            if not at128:
                cos_b, sin_b = _COS_CDEG[raw % 36000], _SIN_CDEG[raw % 36000]
            else:
                step = min(raw // AT128_ADJUST_STEP_UNITS, last_entry)  # (a raw angle past the turn: bad)
                part = (raw - step * AT128_ADJUST_STEP_UNITS) / AT128_ADJUST_STEP_UNITS
                upper = min(step + 1, last_entry)
                turned = ((raw - frame_start[p, first]) % _AT128_TURN) * 2
            first_at = np.uint64(first_unit + first * block_size)
            for c in range(np.uint64(n_channels)):
                at = first_at + c * unit_step
                d0 = data[at] | (np.int64(data[at + one]) << 8)
                refl0 = np.int64(data[at + two])
                if nr == 1:
                    if d0 < lo_p or d0 > hi_p:
                        continue
                    keep[0] = True
                    kinds[0] = single_type
                    units_d[0] = d0
                    units_refl[0] = refl0
                elif nr == 2:
                    at1 = at + block_step
                    d1 = data[at1] | (np.int64(data[at1 + one]) << 8)
                    refl1 = np.int64(data[at1 + two])
                    units_d[0], units_d[1], units_refl[0], units_refl[1] = d0, d1, refl0, refl1
                    brightest = max(refl0, refl1)
                    type0 = types[mode_p, 0, 1 if refl0 == brightest else 0]
                    in0 = lo_p <= d0 <= hi_p
                    drop0 = in0 and (abs(d0 - d1) <= near_p or (d0 == d1 and refl0 == refl1))
                    keep[0] = in0 and not drop0
                    kinds[0] = type0
                    keep[1] = lo_p <= d1 <= hi_p
                    kinds[1] = types[mode_p, 1, 1 if refl1 == brightest else 0] | (type0 if drop0 else 0)
                    if not (keep[0] or keep[1]):
                        continue
                else:
                    brightest = 0
                    for r in range(nr):
                        at_r = at + np.uint64(r) * block_step
                        units_d[r] = data[at_r] | (np.int64(data[at_r + one]) << 8)
                        units_refl[r] = data[at_r + two]
                        brightest = max(brightest, units_refl[r])
                    for r in range(nr):
                        d_r = units_d[r]
                        dropped[r] = False
                        keep[r] = False
                        if d_r < lo_p or d_r > hi_p:
                            continue
                        if r < nr - 1:
                            for o in range(nr):
                                if o != r and (abs(d_r - units_d[o]) <= near_p or (
                                        d_r == units_d[o] and units_refl[r] == units_refl[o])):
                                    dropped[r] = True
                            if dropped[r]:
                                continue
                        kind = types[mode_p, r, 1 if units_refl[r] == brightest else 0]
                        if r == nr - 1:
                            for o in range(nr - 1):
                                if dropped[o]:
                                    kind |= types[mode_p, o, 1 if units_refl[o] == brightest else 0]
                        keep[r] = True
                        kinds[r] = kind
                direction_known = False
                for r in range(nr):
                    if not keep[r]:
                        continue
                    d_r = units_d[r]
                    kind = kinds[r]
                    if not direction_known:
                        direction_known = True
                        if not at128:
                            cos_o, sin_o = pandar_angles[_COS_OFFSET, c], pandar_angles[_SIN_OFFSET, c]
                            dir_x = cos_b * cos_o - sin_b * sin_o
                            dir_y = -(sin_b * cos_o + cos_b * sin_o)
                        else:
                            # whole angle units: the azimuth in integers (1.25x on this loop against the float modulo),
                            # the same values as in float64
                            az_adjust = np.int64(np.rint((1 - part) * at128_azimuth_adjust[c, step] + part *
                                                         at128_azimuth_adjust[c, upper])) * hundredth
                            el_adjust = np.rint((1 - part) * at128_elevation_adjust[c, step] + part *
                                                at128_elevation_adjust[c, upper]) * hundredth
                            turn_units = np.uint64((turned - at128_azimuth[c] + az_adjust) % _AT128_TURN)
                            el = at128_elevation[c] + el_adjust
                            coarse, fine = turn_units // _AT128_FINE_STEPS, turn_units % _AT128_FINE_STEPS
                            cos_c, sin_c = _AT128_COS_COARSE[coarse], _AT128_SIN_COARSE[coarse]
                            cos_f, sin_f = _AT128_COS_FINE[fine], _AT128_SIN_FINE[fine]
                            cos_az = cos_c * cos_f - sin_c * sin_f
                            sin_az = sin_c * cos_f + cos_c * sin_f
                            if el != elevation_seen[c]:
                                el_rad = ((el + _AT128_TURN // 2) % _AT128_TURN - _AT128_TURN // 2) * angle_unit
                                elevation_seen[c] = el
                                cos_elevation_seen[c], sin_elevation_seen[c] = np.cos(el_rad), np.sin(el_rad)
                            cos_el, sin_el = cos_elevation_seen[c], sin_elevation_seen[c]
                    block = np.uint64(first + r)
                    d = f32(d_r * unit_p)
                    if not at128:
                        xy = d * pandar_angles[_COS_ELEVATION, c]
                        xyz[k, 0] = xy * dir_x
                        xyz[k, 1] = xy * dir_y
                        xyz[k, 2] = d * pandar_angles[_SIN_ELEVATION, c]
                    else:
                        xy = np.float64(d) * cos_el
                        xyz[k, 0] = xy * cos_az
                        xyz[k, 1] = -xy * sin_az
                        xyz[k, 2] = np.float64(d) * sin_el
                    distance[k] = d
                    intensity[k] = units_refl[r]
                    laser[k] = c
                    ring[k] = rings[c]
                    azimuth[k] = firing_az
                    return_type[k] = kind
                    time_ns[k] = stamp_p + block_ns[nr, block] + channel_ns[table_rows[p, block], c]
                    packet[k] = packet_p
                    k += one
    return np.int64(k)


def _raw_bounds(dis_unit: np.ndarray, min_m: float, max_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per packet, the least and greatest raw distance whose metres (raw x unit) lie in [min_m, max_m]; at least
    1 (raw 0 is no return)."""
    lo = np.ceil(min_m / dis_unit).astype(np.int64)
    lo = np.maximum(np.where((lo - 1) * dis_unit >= min_m, lo - 1, np.where(lo * dis_unit >= min_m, lo, lo + 1)), 1)
    hi = np.floor(max_m / dis_unit).astype(np.int64)
    hi = np.where((hi + 1) * dis_unit <= max_m, hi + 1, np.where(hi * dis_unit <= max_m, hi, hi - 1))
    return lo, hi


def _raw_below(dis_unit: np.ndarray, threshold_m: float) -> np.ndarray:
    """Per packet, the greatest raw distance difference whose metres are below `threshold_m` (-1: none)."""
    k = np.floor(threshold_m / dis_unit).astype(np.int64)
    return np.where(k * dis_unit < threshold_m, k, k - 1)


def hesai_decoder(model: str, calibration_path: str | Path, **limits: float) -> HesaiDecoder:
    """The decoder of one of HESAI_MODELS with its angle table (AT128: its binary correction file); ValueError
    when the model is unknown or the table does not fit it."""
    fmt = FORMATS.get(model)
    if fmt is None:
        raise ValueError(f"unknown Hesai model {model!r}; known: {', '.join(HESAI_MODELS)}")
    if fmt.fine_azimuth:
        angles: HesaiAngles | AT128Correction = load_at128_correction(calibration_path)
    else:
        angles = load_hesai_angles(calibration_path)
    if angles.num_channels != fmt.n_channels:
        raise ValueError(f"{calibration_path}: {angles.num_channels} channels, a {model} has {fmt.n_channels}")
    return HesaiDecoder(fmt, angles, **limits)


def hesai_imu_samples(packets: list[bytes]) -> dict[str, np.ndarray]:
    """The IMU readings in the tails of Pandar128E4X packets (the only model here that carries one): `time_ns`
    (the packet's UTC stamp), `imu_timestamp` (the IMU's own counter), `angular_velocity_rad_s` and
    `linear_acceleration_m_s2` (n, 3); a reading repeated in consecutive packets is given once. Layout from
    nebula's 128E3X/E4X tail and its IMU decoder: acceleration value x unit x 0.001 mg, angular velocity value x
    unit x 0.01 mdps; the values read as signed 16 bit (nebula's struct comments say unsigned; not checked
    against a real packet)."""
    fmt = FORMATS["hesai-pandar128e4x"]
    good = [p[: min(fmt.sizes)] for p in packets if format_of(p) is fmt]
    batch = np.frombuffer(b"".join(good), np.uint8).reshape(-1, min(fmt.sizes))
    time_ns, ok = packet_times_ns(fmt, batch)
    at = fmt.imu_at
    imu_time = u16(batch, at + 6) | (u16(batch, at + 8) << 16)
    fresh = ok & (np.diff(imu_time, prepend=-1) != 0)  # within this call
    batch, time_ns, imu_time = batch[fresh], time_ns[fresh], imu_time[fresh]
    axes = np.stack([u16(batch, at + 10 + 2 * i) for i in range(6)], axis=1)
    axes = np.where(axes >= 32768, axes - 65536, axes).astype(np.float64)  # signed 16 bit
    accel_unit = u16(batch, at + 2)[:, None] * 1e-6 * 9.80665  # value * unit * 0.001 mg
    gyro_unit = np.deg2rad(u16(batch, at + 4)[:, None] * 1e-5)  # value * unit * 0.01 mdps
    return {
        "time_ns": time_ns,
        "imu_timestamp": imu_time,
        "angular_velocity_rad_s": axes[:, 3:] * gyro_unit,
        "linear_acceleration_m_s2": axes[:, :3] * accel_unit,
    }
