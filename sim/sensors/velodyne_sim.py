"""The simulated Velodyne (VLP-16, VLP-32C, VLS-128) of a calibration file, as a LidarRig: a column is one firing
sequence of all lasers (a packet holds 384 returns: 24, 12 or 3 sequences), each laser's ray at the azimuth the
head has turned to at its own firing time (the manual's firing timing, velodyne_models.MODELS) less its
rot_correction, up by its vert_correction, the head turning `rate_hz` times a second from azimuth 0 at each scan's
start. A scan is the whole packets that fit in one rotation; they are encoded into the sensor's single-return
packets (drivers/lidar/velodyne_encoder.py), stamped in microseconds past the hour as the sensor does, and published
at that time unwrapped, as the vendor driver publishes them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from daemon.spine.config import LidarConfig
from drivers.lidar.lidar_models import VENDOR_LIDARS
from drivers.lidar.velodyne_encoder import encode_velodyne_packets, velodyne_model
from drivers.lidar.velodyne_models import BLOCKS_PER_PACKET, RETURNS_PER_BLOCK
from sim.sensors.lidar_sim import LidarRig, LidarScanSim

SLOTS = BLOCKS_PER_PACKET * RETURNS_PER_BLOCK  # returns per packet
SIMULATED_VELODYNES = ("velodyne-vlp16", "velodyne-vlp32c", "velodyne-vls128")  # not the HDL-64E (upper/lower banks)


def velodyne_rig(config: LidarConfig, calibration_path: str | Path) -> LidarRig:
    if config.model not in SIMULATED_VELODYNES:
        raise ValueError(f"the simulator has no {config.model}: it simulates the Ouster OS-128 and the Velodyne "
                         f"{', '.join(SIMULATED_VELODYNES)}")
    decoder = VENDOR_LIDARS[config.model].load_decoder(Path(calibration_path), config)
    cal = decoder.calibration
    model = velodyne_model(cal.num_lasers)
    lasers = cal.num_lasers
    per_packet = SLOTS // lasers  # firing sequences per packet
    slot = np.arange(SLOTS)
    block, channel = slot // RETURNS_PER_BLOCK, slot % RETURNS_PER_BLOCK
    fire_s = model.firing_time_s[block, channel].astype(np.float64)  # (384,) after the packet's stamp
    sequence_s = float(fire_s[lasers] - fire_s[0])  # one firing of every laser
    packet_s = sequence_s * per_packet
    packets = int(1.0 / config.rate_hz // packet_s)  # whole packets in one rotation
    rate_cdeg_s = 36000.0 * config.rate_hz
    # the block azimuth the packet carries: the head's at its block's reference firing (a VLS-128's 4 banks of a
    # sequence share their sequence's), in whole 0.01 degrees; each return's azimuth is that plus the turn since
    reference = block // 4 * 4 if lasers == 128 else block
    t = (np.arange(packets)[:, None] * packet_s + fire_s[None, :])  # (P, 384) after the scan's first packet stamp
    t_reference = np.arange(packets)[:, None] * packet_s + model.firing_time_s[reference, 0][None, :]
    block_azimuth = np.floor(rate_cdeg_s * t_reference + 0.5)
    azimuth = np.radians((block_azimuth + rate_cdeg_s * (t - t_reference)) / 100.0)
    laser = slot % lasers if lasers < 128 else 32 * (block % 4) + channel
    a = azimuth - cal.rot_correction_rad[laser][None, :]
    v = np.broadcast_to(cal.vert_correction_rad[laser][None, :], a.shape)
    rays = np.stack([np.cos(v) * np.cos(a), -np.cos(v) * np.sin(a), np.sin(v)], axis=-1)  # (P, 384, 3)
    # columns: (packet, sequence); rows: lasers by id
    sequence = slot // lasers if lasers < 128 else block // 4
    direction = np.zeros((packets * per_packet, lasers, 3), np.float32)
    column = np.arange(packets)[:, None] * per_packet + sequence[None, :]
    direction[column, np.broadcast_to(laser[None, :], column.shape)] = rays
    first_slot = np.array([np.flatnonzero(sequence == q)[0] for q in range(per_packet)])
    column_offset = (np.arange(packets)[:, None] * packet_s + fire_s[first_slot][None, :]).ravel()
    stamp_offset_ns = round(float(model.firing_time_s[0, 0]) * 1e9)  # the first firing after the stamp
    resolution = cal.distance_resolution_m

    def encode(scan: LidarScanSim, column_stamp_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        slots = np.arange(packets)[:, None] * per_packet + sequence[None, :]  # column of each packet's slot
        rng_m = scan.range_mm[np.broadcast_to(laser[None, :], slots.shape), slots] / 1000.0  # (P, 384)
        raw = np.where(rng_m > 0, np.rint((rng_m - cal.dist_correction_m[laser][None, :]) / resolution), 0)
        raw = np.where(raw <= 65535, raw, 0).reshape(packets, BLOCKS_PER_PACKET, RETURNS_PER_BLOCK)  # beyond: none
        reflect = scan.reflectivity[np.broadcast_to(laser[None, :], slots.shape), slots]
        stamps_ns = column_stamp_ns[::per_packet].astype(np.int64) - stamp_offset_ns
        stamps_us = stamps_ns // 1000
        out = encode_velodyne_packets(model, block_azimuth.reshape(packets, BLOCKS_PER_PACKET, -1)[:, :, 0], raw,
                                      reflect.reshape(raw.shape), stamps_us)
        return out, stamps_us * 1000

    return LidarRig(np.ascontiguousarray(direction), np.zeros_like(direction), config.extrinsics.matrix(),
                    column_offset, per_packet, encode)
