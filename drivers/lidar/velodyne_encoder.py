"""Velodyne data packets made from returns (the simulator's sensor, tests): 12 blocks of 32 returns with their
bank flags and azimuths, the timestamp (microseconds past the hour) and the factory bytes of a single
(strongest) return packet. The inverse of velodyne_decoder for what it decodes."""

from __future__ import annotations

import numpy as np

from drivers.lidar.velodyne_models import (
    BLOCKS_PER_PACKET,
    MODELS,
    PACKET_SIZE,
    RETURN_STRONGEST,
    RETURNS_PER_BLOCK,
    VelodyneModel,
)

HOUR_US = 3600 * 10**6
_BANK_FLAGS = (0xEEFF, 0xDDFF, 0xCCFF, 0xBBFF)  # lasers 0-31, 32-63, ... (VLS-128); the others use the first


def velodyne_model(num_lasers: int) -> VelodyneModel:
    """The model with this many lasers (ValueError for none)."""
    for model in MODELS.values():
        if model.num_lasers == num_lasers:
            return model
    raise ValueError(f"no Velodyne model with {num_lasers} lasers is decoded here")


def encode_velodyne_packets(model: VelodyneModel, block_azimuth_cdeg: np.ndarray, raw_distance: np.ndarray,
                            intensity: np.ndarray, timestamp_us: np.ndarray) -> np.ndarray:
    """(P, 1206) uint8 packets from per packet: block azimuths (P, 12) in 0.01 degrees, raw distances (P, 12, 32)
    in the calibration's range units (0: no return), intensities (P, 12, 32) and the timestamp (P,), taken
    modulo the hour."""
    n = len(timestamp_us)
    out = np.zeros((n, PACKET_SIZE), np.uint8)
    blocks = out[:, :1200].reshape(n, BLOCKS_PER_PACKET, 100)
    bank = np.arange(BLOCKS_PER_PACKET) % 4 if model.num_lasers == 128 else np.zeros(BLOCKS_PER_PACKET, int)
    flags = np.array(_BANK_FLAGS, np.uint16)[bank]
    blocks[:, :, 0:2] = flags.astype("<u2").view(np.uint8).reshape(BLOCKS_PER_PACKET, 2)[None]
    blocks[:, :, 2:4] = (np.asarray(block_azimuth_cdeg) % 36000).astype("<u2")[..., None].view(np.uint8)
    returns = blocks[:, :, 4:].reshape(n, BLOCKS_PER_PACKET, RETURNS_PER_BLOCK, 3)
    returns[..., 0:2] = np.asarray(raw_distance).astype("<u2")[..., None].view(np.uint8)
    returns[..., 2] = np.clip(intensity, 0, 255).astype(np.uint8)
    out[:, 1200:1204] = (np.asarray(timestamp_us, np.int64) % HOUR_US).astype("<u4")[:, None].view(np.uint8)
    out[:, 1204] = RETURN_STRONGEST
    out[:, 1205] = model.product_id
    return out
