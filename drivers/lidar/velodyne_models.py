"""Velodyne models as their packets show them: the packet's size and blocks, the factory bytes (product id, return
mode) and each model's firing time of every return after the packet's timestamp (the manuals' timing tables)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PACKET_SIZE = 1206
BLOCKS_PER_PACKET = 12
RETURNS_PER_BLOCK = 32
RETURN_STRONGEST, RETURN_LAST, RETURN_DUAL = 0x37, 0x38, 0x39


@dataclass(frozen=True)
class VelodyneModel:
    name: str
    product_id: int | None  # factory byte 1205; None: the model does not set it (HDL-64E)
    num_lasers: int
    firing_time_s: np.ndarray  # (12, 32) float32, time of each return after the packet's timestamp


def _vlp16_timing() -> np.ndarray:
    # VLP-16 manual: 16 firings of 2.304 us, a 55.296 us cycle; a block holds two cycles.
    block, channel = np.meshgrid(np.arange(12), np.arange(32), indexing="ij")
    return (55.296e-6 * (2 * block + channel // 16) + 2.304e-6 * (channel % 16)).astype(np.float32)


def _vlp32c_timing() -> np.ndarray:
    # VLP-32C manual: lasers fire in pairs, 16 firings of 2.304 us, a 55.296 us cycle per block.
    block, channel = np.meshgrid(np.arange(12), np.arange(32), indexing="ij")
    return (55.296e-6 * block + 2.304e-6 * (channel // 2)).astype(np.float32)


def _vls128_timing() -> np.ndarray:
    # VLS-128: groups of 8 lasers fire every 2.66666 us, 20 group slots a sequence (16 groups plus
    # maintenance after groups 8 and 16); 4 blocks (banks) make one sequence; timestamp 7 us late.
    block, channel = np.meshgrid(np.arange(12), np.arange(32), indexing="ij")
    group_time = 2.66666e-6
    laser = 32 * (block % 4) + channel
    t = (block // 4) * 20 * group_time + (laser // 8 + laser // 64 * 2) * group_time - 7e-6
    return t.astype(np.float32)


def _hdl64e_timing(cycle_us: float, step_us: float, pattern_us: tuple[float, ...]) -> np.ndarray:
    # HDL-64E S2/S3 manuals' laser firing table, as velodyne-decoder builds it: an upper and a lower block
    # fire together; in a block, four lasers `pattern_us` apart every `step_us`; a firing every `cycle_us`.
    block, channel = np.meshgrid(np.arange(12), np.arange(32), indexing="ij")
    pattern = np.array(pattern_us)[channel % 4]
    return ((cycle_us * (block // 2) + step_us * (channel // 4) + pattern) * 1e-6).astype(np.float32)


MODELS = {
    m.product_id: m
    for m in (
        VelodyneModel("VLP-16", 0x22, 16, _vlp16_timing()),
        VelodyneModel("VLP-32C", 0x28, 32, _vlp32c_timing()),
        VelodyneModel("VLS-128", 0xA1, 128, _vls128_timing()),
    )
}
# The HDL-64E puts a rotating status byte where the others have their factory bytes: its model is configured.
HDL64E_MODELS = {
    m.name: m
    for m in (
        VelodyneModel("HDL-64E S2", None, 64, _hdl64e_timing(48.0, 6.0, (0.0, 1.26, 2.46, 3.66))),
        VelodyneModel("HDL-64E S3", None, 64, _hdl64e_timing(57.6, 7.2, (0.0, 1.3, 2.5, 3.7))),
    )
}
