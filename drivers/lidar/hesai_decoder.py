"""Hesai data packets (Pandar40P, Pandar64, PandarQT128, PandarXT32, Pandar128E4X/OT128, PandarAT128) decoded a
batch at a time with numpy: returns per firing from the tail's return mode, range, reflectivity, channel,
ring, per-point firing time on the sensor's UTC clock and xyz in the sensor frame (x forward, y left, z up).
Foreign, truncated and malformed datagrams are counted per reason and skipped. `hesai_decoder(model, path)`
builds one from the model's angle table; `hesai_imu_samples` reads the IMU fields the 128E4X tail carries."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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
from drivers.lidar.packet_decoding import DecodedPoints, PacketCheck, empty_points

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
_COS_CDEG = np.cos(np.deg2rad(np.arange(36000) * 0.01)).astype(np.float32)
_SIN_CDEG = np.sin(np.deg2rad(np.arange(36000) * 0.01)).astype(np.float32)


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
        if isinstance(angles, HesaiAngles):  # per-channel cosines and sines, float32
            elevation, offset = np.deg2rad(angles.elevation_deg), np.deg2rad(angles.azimuth_offset_deg)
            self._cos_elevation, self._sin_elevation = (f(elevation).astype(np.float32) for f in (np.cos, np.sin))
            self._cos_offset, self._sin_offset = (f(offset).astype(np.float32) for f in (np.cos, np.sin))
        self._types = return_type_table(fmt.first_last_reversed)

    @property
    def model(self) -> str:
        return self.format.model

    def check(self, packets: list[bytes]) -> PacketCheck:
        """Which datagrams are this sensor's data packets, their UTC stamps and their first block's azimuth."""
        counts: dict[str, int] = {}
        batch, index = self._accepted(packets, counts)
        accepted = np.zeros(len(packets), bool)
        accepted[index] = True
        time_ns = np.zeros(len(packets), np.int64)
        azimuth = np.zeros(len(packets), np.int32)
        time_ns[index] = packet_times_ns(self.format, batch)[0]
        azimuth[index] = self._firing_azimuth(self._block_azimuth(batch)[:, :1])[:, 0]
        return PacketCheck(accepted, time_ns, azimuth, {k: v for k, v in counts.items() if v})

    def decode(self, packets: list[bytes]) -> DecodedPoints:
        counts = {"packets_in": len(packets), "packets_decoded": 0} | dict.fromkeys(REASONS, 0)
        batch, index = self._accepted(packets, counts)
        counts["packets_decoded"] = len(index)
        if len(index) == 0:
            return empty_points(counts, self.model)
        points = self._decode_points(batch, index)
        points.counts = counts
        return points

    def _accepted(self, packets: list[bytes], counts: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
        """The model's good packets as an (n, size) uint8 array (the optional trailing fields cut off), and their
        positions in `packets`; the others counted by reason."""
        fmt = self.format
        size = min(fmt.sizes)
        sized = [i for i, p in enumerate(packets) if len(p) in fmt.sizes]
        for i in set(range(len(packets))).difference(sized):
            other = format_of(packets[i])
            reason = FOREIGN_MODEL if other is not None and other is not fmt else WRONG_SIZE
            counts[reason] = counts.get(reason, 0) + 1
        index = np.array(sized, dtype=np.int64)
        batch = np.frombuffer(b"".join(packets[i][:size] for i in sized), np.uint8).reshape(-1, size)
        header_ok = np.all([batch[:, at] == value for at, value in fmt.header], axis=0)
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
        checks.append((BAD_TIMESTAMP, packet_times_ns(fmt, batch)[1]))
        good = np.ones(len(batch), bool)
        for reason, ok in checks:
            counts[reason] = counts.get(reason, 0) + int((good & ~ok).sum())
            good &= ok
        return batch[good], index[good]

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

    def _decode_points(self, batch: np.ndarray, index: np.ndarray) -> DecodedPoints:
        """Units looked at densely, per packet, firing (block group), return and channel; the kept ones picked
        out in nebula's order: packet, firing, channel, return."""
        fmt = self.format
        n, f32 = len(batch), np.float32
        blocks = batch[:, fmt.first_block : fmt.first_block + fmt.n_blocks * fmt.block_size]
        blocks = blocks.reshape(n, fmt.n_blocks, fmt.block_size)
        units = blocks[:, :, fmt.first_unit : fmt.first_unit + fmt.n_channels * fmt.unit_size]
        units = units.reshape(n, fmt.n_blocks, fmt.n_channels, fmt.unit_size)
        raw_distance = units[:, :, :, 0].astype(np.int32) | (units[:, :, :, 1].astype(np.int32) << 8)
        reflectivity = units[:, :, :, 2]
        dis_unit = np.full(n, 0.004) if fmt.dis_unit_at is None else batch[:, fmt.dis_unit_at] * 1e-3
        mode = batch[:, fmt.return_mode_at]
        n_returns = N_RETURNS[mode]
        per_packet = fmt.n_blocks * fmt.n_channels
        parts = []
        for nr in np.unique(n_returns):
            rows = np.flatnonzero(n_returns == nr)
            unit, return_type = self._kept_returns(int(nr), mode[rows], raw_distance[rows], reflectivity[rows],
                                                   dis_unit[rows])
            parts.append((rows[unit // per_packet] * per_packet + unit % per_packet, return_type))
        if len(parts) > 1:
            unit, return_type = (np.concatenate([p[i] for p in parts]) for i in range(2))
            order = np.argsort(unit // per_packet, kind="stable")
            unit, return_type = unit[order], return_type[order]
        else:
            unit, return_type = parts[0]
        row, channel = unit // per_packet, unit % fmt.n_channels
        block = unit // fmt.n_channels % fmt.n_blocks
        distance = (raw_distance.ravel()[unit] * dis_unit[row]).astype(f32)
        raw_azimuth = self._block_azimuth(batch)[row, block - block % n_returns[row]]
        firing = fmt.firing
        firing_ns = firing.block_ns(fmt.n_blocks)[n_returns[row], block]
        firing_ns += firing.channel_ns[firing.rows(n_returns, batch, fmt.n_blocks)[row, block], channel]
        return DecodedPoints(
            model=self.model,
            xyz=self._xyz(distance, raw_azimuth, channel),
            distance_m=distance,
            intensity=reflectivity.ravel()[unit].astype(f32),
            laser_id=channel.astype(np.uint16),
            ring=self.angles.ring[channel],
            azimuth_cdeg=self._firing_azimuth(raw_azimuth).astype(np.uint16),
            return_type=return_type,
            timestamp_ns=packet_times_ns(fmt, batch)[0][row] + firing_ns,
            packet_index=index[row],
        )

    def _kept_returns(self, nr: int, mode: np.ndarray, raw_distance: np.ndarray, reflectivity: np.ndarray,
                      dis_unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices into the (m, blocks, channels) units of m packets with `nr` returns per firing of the
        returns kept, in order of packet, firing, channel, return; and their return types. Ranges are compared
        in raw units: per packet, the raw bounds that the metre limits give."""
        m, n_blocks, n_channels = raw_distance.shape
        shape = (m, n_blocks // nr, nr, n_channels)  # packet, firing, return, channel
        d = raw_distance.reshape(shape)
        lo, hi = _raw_bounds(dis_unit, self.min_range_m, self.max_range_m)
        keep = (d >= lo[:, None, None, None]) & (d <= hi[:, None, None, None])  # lo >= 1: raw 0 is no return
        if nr == 1:
            unit = np.flatnonzero(keep)
            return unit, self._types[mode[unit // (n_blocks * n_channels)], 0, 1]
        refl = reflectivity.reshape(shape)
        strongest = (refl == refl.max(axis=2, keepdims=True)).ravel()
        # A return equal to or within the threshold of another of its firing is dropped unless it is the last;
        # the last then stands for it and carries its type bits too (nebula keeps only the last).
        near_raw = _raw_below(dis_unit, self.dual_threshold_m)[:, None, None]
        dropped = np.zeros_like(keep)
        for r in range(nr - 1):
            for other in range(nr):
                if other != r:
                    dropped[:, :, r] |= np.abs(d[:, :, r] - d[:, :, other]) <= near_raw
                    if near_raw.min() < 0:  # else an equal distance is near already
                        dropped[:, :, r] |= (d[:, :, r] == d[:, :, other]) & (refl[:, :, r] == refl[:, :, other])
        dropped &= keep
        keep &= ~dropped
        t = np.flatnonzero(keep.transpose(0, 1, 3, 2))  # ((packet, firing), channel, return)
        ret, channel, firing = t % nr, t // nr % n_channels, t // (nr * n_channels)
        unit = (firing * nr + ret) * n_channels + channel
        mode = mode[unit // (n_blocks * n_channels)]
        return_type = self._types[mode, ret, strongest[unit].astype(np.intp)]
        last = np.flatnonzero(ret == nr - 1)
        dropped = dropped.ravel()
        for r in range(nr - 1):
            other = unit[last] - (nr - 1 - r) * n_channels
            was = last[dropped[other]]
            return_type[was] |= self._types[mode[was], r, strongest[other[dropped[other]]].astype(np.intp)]
        return unit, return_type

    def _xyz(self, distance: np.ndarray, raw_azimuth: np.ndarray, channel: np.ndarray) -> np.ndarray:
        """x forward, y left, z up of each return, float32. Hesai's azimuth runs clockwise seen from above, 0
        forward. Pandar: the block azimuth's cosine and sine from a 0.01 degree table, the channel's offset added
        by the angle sum formulas."""
        f32 = np.float32
        xyz = np.empty((len(distance), 3), f32)
        if self.format.fine_azimuth:
            azimuth, elevation = self._angles_rad(raw_azimuth, channel)
            xy = distance * np.cos(elevation)
            xyz[:, 0], xyz[:, 1], xyz[:, 2] = xy * np.cos(azimuth), -xy * np.sin(azimuth), distance * np.sin(elevation)
            return xyz
        cos_b, sin_b = _COS_CDEG[raw_azimuth % 36000], _SIN_CDEG[raw_azimuth % 36000]
        cos_o, sin_o = self._cos_offset[channel], self._sin_offset[channel]
        xy = distance * self._cos_elevation[channel]
        np.multiply(xy, cos_b * cos_o - sin_b * sin_o, out=xyz[:, 0])
        np.multiply(xy, -(sin_b * cos_o + cos_b * sin_o), out=xyz[:, 1])
        np.multiply(distance, self._sin_elevation[channel], out=xyz[:, 2])
        return xyz

    def _angles_rad(self, raw_azimuth: np.ndarray, channel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """AT128: corrected azimuth and elevation of each point from the correction file. The azimuth is twice
        the motor angle past the mirror's frame start, less the channel's azimuth, plus the adjustment that
        the file gives every 2 degrees of motor angle, interpolated (nebula's rule; past the last entry the
        last one is taken)."""
        c = self.angles
        start = c.frame_start[self._at128_field(raw_azimuth)]
        step = raw_azimuth // AT128_ADJUST_STEP_UNITS
        k = (raw_azimuth - step * AT128_ADJUST_STEP_UNITS) / AT128_ADJUST_STEP_UNITS
        upper = np.minimum(step + 1, AT128_ADJUST_ENTRIES - 1)

        def adjust(table: np.ndarray) -> np.ndarray:  # 0.01 degree -> angle units
            hundredths = np.round((1 - k) * table[channel, step] + k * table[channel, upper])
            return hundredths * (AT128_ANGLE_UNITS_PER_DEG // 100)

        azimuth = ((raw_azimuth - start) % _AT128_TURN) * 2 - c.azimuth[channel] + adjust(c.azimuth_adjust)
        elevation = c.elevation[channel] + adjust(c.elevation_adjust)
        unit = np.pi / (180 * AT128_ANGLE_UNITS_PER_DEG)
        return (azimuth % _AT128_TURN) * unit, ((elevation + _AT128_TURN // 2) % _AT128_TURN - _AT128_TURN // 2) * unit


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
