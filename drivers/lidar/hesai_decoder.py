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
    DUAL_FIRST_LAST,
    DUAL_FIRST_SECOND,
    DUAL_FIRST_STRONGEST,
    DUAL_LAST_STRONGEST,
    DUAL_STRONGEST_SECOND,
    FORMATS,
    HESAI_MODELS,
    RETURN_MODES,
    SINGLE_LAST,
    SINGLE_STRONGEST,
    HesaiFormat,
    format_of,
    packet_times_ns,
    u16,
)
from drivers.lidar.packet_decoding import (
    RETURN_TYPE_LAST,
    RETURN_TYPE_OTHER,
    RETURN_TYPE_STRONGEST,
    DecodedPoints,
    PacketCheck,
    empty_points,
)

__all__ = ["HESAI_MODELS", "HesaiDecoder", "hesai_decoder", "hesai_imu_samples"]

# Reasons a datagram is skipped, as DecodedPoints.counts and PacketCheck.counts name them.
WRONG_SIZE = "wrong_size"  # no Hesai data packet size of this model (or truncated)
FOREIGN_MODEL = "foreign_model"  # another Hesai model's data packet
BAD_HEADER = "bad_header"  # the model's size, but not its header signature, laser and block counts
BAD_BLOCK_FLAG = "bad_block_flag"  # a block's start flag is wrong (Pandar40P)
UNKNOWN_RETURN_MODE = "unknown_return_mode"  # a return mode byte of no mode, or not fitting the blocks
BAD_TIMESTAMP = "bad_timestamp"  # the tail's date or microseconds are out of range
REASONS = (WRONG_SIZE, FOREIGN_MODEL, BAD_HEADER, BAD_BLOCK_FLAG, UNKNOWN_RETURN_MODE, BAD_TIMESTAMP)

_AT128_TURN = 360 * AT128_ANGLE_UNITS_PER_DEG


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
        if isinstance(angles, HesaiAngles):
            self._elevation = np.deg2rad(angles.elevation_deg)
            self._azimuth_offset = np.deg2rad(angles.azimuth_offset_deg)

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
        checks = [(BAD_HEADER, np.all([batch[:, at] == value for at, value in fmt.header], axis=0))]
        if fmt.block_flag:
            starts = fmt.first_block + fmt.block_size * np.arange(fmt.n_blocks)
            flag = np.frombuffer(fmt.block_flag, np.uint8)
            checks.append((BAD_BLOCK_FLAG, np.all(batch[:, starts[:, None] + np.arange(2)] == flag, axis=(1, 2))))
        mode = batch[:, fmt.return_mode_at]
        n_returns = np.array([RETURN_MODES.get(int(m), 0) for m in range(256)])[mode]
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
        """Units computed densely as (n, groups, channels, returns), then the kept ones picked out, in nebula's
        order: packet, firing (block group), channel, return."""
        fmt = self.format
        n, f32 = len(batch), np.float32
        blocks = batch[:, fmt.first_block : fmt.first_block + fmt.n_blocks * fmt.block_size]
        blocks = blocks.reshape(n, fmt.n_blocks, fmt.block_size)
        units = blocks[:, :, fmt.first_unit : fmt.first_unit + fmt.n_channels * fmt.unit_size]
        units = units.reshape(n, fmt.n_blocks, fmt.n_channels, fmt.unit_size)
        raw_distance = u16(units, 0)
        reflectivity = units[:, :, :, 2]
        dis_unit = np.full(n, 0.004) if fmt.dis_unit_at is None else batch[:, fmt.dis_unit_at] * 1e-3
        mode = batch[:, fmt.return_mode_at]
        n_returns = np.array([RETURN_MODES.get(int(m), 0) for m in mode])
        stamp_ns = packet_times_ns(fmt, batch)[0]
        firing_ns = fmt.firing_ns(n_returns, batch)  # (n, blocks, channels)
        block_azimuth = self._block_azimuth(batch)
        parts = []
        for nr in np.unique(n_returns):
            rows = np.flatnonzero(n_returns == nr)
            parts.append(self._decode_mode_group(
                rows, int(nr), mode[rows], raw_distance[rows], reflectivity[rows], dis_unit[rows],
                block_azimuth[rows], stamp_ns[rows, None, None] + firing_ns[rows]))
        if len(parts) > 1:
            order = np.argsort(np.concatenate([p["row"] for p in parts]), kind="stable")
            merged = {k: np.concatenate([p[k] for p in parts])[order] for k in parts[0]}
        else:
            merged = parts[0]
        row, channel, distance = merged["row"], merged["channel"], merged["distance"]
        azimuth, elevation = self._angles_rad(merged["raw_azimuth"], channel)
        xy = distance * np.cos(elevation)
        xyz = np.stack([xy * np.cos(azimuth), -xy * np.sin(azimuth), distance * np.sin(elevation)], axis=1)
        return DecodedPoints(
            model=self.model,
            xyz=xyz.astype(f32),
            distance_m=distance.astype(f32),
            intensity=merged["reflectivity"].astype(f32),
            laser_id=channel.astype(np.uint16),
            ring=self.angles.ring[channel],
            azimuth_cdeg=self._firing_azimuth(merged["raw_azimuth"]).astype(np.uint16),
            return_type=merged["return_type"],
            timestamp_ns=merged["time_ns"],
            packet_index=index[row],
        )

    def _decode_mode_group(self, rows, nr, mode, raw_distance, reflectivity, dis_unit, block_azimuth, time_ns):
        """The kept returns of packets with `nr` returns per firing, as flat arrays."""
        m, n_blocks, n_channels = raw_distance.shape
        shape = (m, n_blocks // nr, nr, n_channels)

        def grouped(a: np.ndarray) -> np.ndarray:  # (m, blocks, channels) -> (m, groups, channels, returns)
            return a.reshape(shape).transpose(0, 1, 3, 2)

        d_raw, refl = grouped(raw_distance), grouped(reflectivity)
        distance = d_raw * dis_unit[:, None, None, None]
        keep = (d_raw != 0) & (distance >= self.min_range_m) & (distance <= self.max_range_m)
        return_type = self._return_types(mode, refl, nr)
        if nr > 1:
            # A return equal to or within the threshold of another one of its firing is dropped unless it is
            # the last; the last one then stands for it and carries its type bits too.
            dropped = np.zeros_like(keep)
            for other in range(nr):
                same = (d_raw == d_raw[..., other : other + 1]) & (refl == refl[..., other : other + 1])
                near = np.abs(distance - distance[..., other : other + 1]) < self.dual_threshold_m
                dropped |= (same | near) & (np.arange(nr) != other)
            dropped &= keep & (np.arange(nr) < nr - 1)
            keep &= ~dropped
            return_type[..., -1] |= np.bitwise_or.reduce(np.where(dropped, return_type, 0), axis=-1).astype(np.uint8)
        row, group, channel, ret = np.nonzero(keep)
        block = group * nr + ret
        return {
            "row": rows[row],
            "channel": channel,
            "distance": distance[row, group, channel, ret],
            "reflectivity": refl[row, group, channel, ret],
            "raw_azimuth": block_azimuth[row, group * nr],
            "return_type": return_type[row, group, channel, ret],
            "time_ns": time_ns[row, block, channel],
        }

    def _return_types(self, mode: np.ndarray, refl: np.ndarray, nr: int) -> np.ndarray:
        """(m, groups, channels, returns) RETURN_TYPE_* bits of each return by the packet's return mode."""
        S, L, O = RETURN_TYPE_STRONGEST, RETURN_TYPE_LAST, RETURN_TYPE_OTHER
        mode = mode[:, None, None, None]
        if nr == 1:
            single = np.where(mode == SINGLE_STRONGEST, S, np.where(mode == SINGLE_LAST, L, O))
            return np.broadcast_to(single, refl.shape).astype(np.uint8)
        if nr == 3:  # first, last, strongest
            return np.broadcast_to(np.array([O, L, S], np.uint8), refl.shape).copy()
        strongest = refl == refl.max(axis=-1, keepdims=True)
        by_mode = {  # (first block, second block); 0: strongest or not decides
            DUAL_LAST_STRONGEST: (L, 0),
            DUAL_FIRST_STRONGEST: (O, 0),
            DUAL_FIRST_SECOND: (O, O),
            DUAL_STRONGEST_SECOND: (S, O),
            DUAL_FIRST_LAST: (L, O) if self.format.first_last_reversed else (O, L),
        }
        types = np.zeros(refl.shape, np.uint8)
        for code, base in by_mode.items():
            types = np.where(mode == code, np.array(base, np.uint8), types)
        by_strength = np.isin(mode, [DUAL_LAST_STRONGEST, DUAL_FIRST_STRONGEST])
        types |= np.where(by_strength & strongest, S, 0).astype(np.uint8)
        types |= np.where(by_strength & ~strongest & (np.arange(2) == 1), O, 0).astype(np.uint8)
        return types

    def _angles_rad(self, raw_azimuth: np.ndarray, channel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corrected azimuth (clockwise from forward, as Hesai counts it) and elevation of each point."""
        if not self.format.fine_azimuth:
            return np.deg2rad(raw_azimuth * 0.01) + self._azimuth_offset[channel], self._elevation[channel]
        c = self.angles
        start = c.frame_start[self._at128_field(raw_azimuth)]
        step = raw_azimuth // AT128_ADJUST_STEP_UNITS
        k = (raw_azimuth - step * AT128_ADJUST_STEP_UNITS) / AT128_ADJUST_STEP_UNITS
        upper = np.minimum(step + 1, AT128_ADJUST_ENTRIES - 1)

        def adjust(table: np.ndarray) -> np.ndarray:  # 0.01 degree -> angle units
            return np.round((1 - k) * table[channel, step] + k * table[channel, upper]) * (AT128_ANGLE_UNITS_PER_DEG
                                                                                           // 100)

        azimuth = ((raw_azimuth - start) % _AT128_TURN) * 2 - c.azimuth[channel] + adjust(c.azimuth_adjust)
        elevation = c.elevation[channel] + adjust(c.elevation_adjust)
        unit = np.pi / (180 * AT128_ANGLE_UNITS_PER_DEG)
        return (azimuth % _AT128_TURN) * unit, ((elevation + _AT128_TURN // 2) % _AT128_TURN - _AT128_TURN // 2) * unit


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
    `linear_acceleration_m_s2` (n, 3); a reading repeated in consecutive packets is given once."""
    fmt = FORMATS["hesai-pandar128e4x"]
    good = [p[: min(fmt.sizes)] for p in packets if format_of(p) is fmt]
    batch = np.frombuffer(b"".join(good), np.uint8).reshape(-1, min(fmt.sizes))
    time_ns, ok = packet_times_ns(fmt, batch)
    at = fmt.imu_at
    imu_time = u16(batch, at + 6) | (u16(batch, at + 8) << 16)
    fresh = ok & np.concatenate([[True], imu_time[1:] != imu_time[:-1]])
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
