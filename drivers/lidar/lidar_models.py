"""The Lidar models decoded from packets by a vendor decoder (everything but Ouster, whose driver and decoder are
their own): per config model name, how its decoder is built from the sensor's calibration file (`metadata_file`:
Velodyne YAML, Hesai or RoboSense angle CSV), its UDP port, and whether its packet stamps wrap (Velodyne counts
microseconds past the top of the hour; the others stamp UTC), and the IMU readings its packets carry, if any."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemon.spine.config import ConfigError, LidarConfig, resolve_path
from drivers.lidar.hesai_decoder import HESAI_MODELS, hesai_decoder, hesai_imu_samples
from drivers.lidar.packet_decoding import PacketDecoder
from drivers.lidar.robosense_decoder import ROBOSENSE_MODELS, robosense_decoder
from drivers.lidar.velodyne_decoder import VELODYNE_MODELS, velodyne_decoder

HOUR_NS = 3600 * 10**9


@dataclass(frozen=True)
class VendorLidar:
    model: str  # the config's name for it
    # from the calibration file and the sensor's config; ValueError when the file does not fit the model
    load_decoder: Callable[[Path, LidarConfig], PacketDecoder]
    stamp_period_ns: int | None  # the packet stamps count modulo this (None: absolute UTC)
    # the IMU readings its data packets carry (time_ns: the packet's stamp, angular_velocity_rad_s,
    # linear_acceleration_m_s2, imu_timestamp: the IMU's own counter), None: it has none
    imu_readings: Callable[[list[bytes]], dict[str, np.ndarray]] | None = None


# VLS-128 ranges come in 4 mm units (its manual); a calibration file's other value is not used: the shared VLS128.yaml
# says 7 mm, which puts every point 1.75x too far against the vendor project's reference cloud
VLS128_DISTANCE_RESOLUTION_M = 0.004


def _velodyne(path: Path, config: LidarConfig) -> PacketDecoder:
    decoder = velodyne_decoder(config.model, path)
    if config.model == "velodyne-vls128":
        decoder.calibration.distance_resolution_m = VLS128_DISTANCE_RESOLUTION_M
    return decoder


def _hesai(path: Path, config: LidarConfig) -> PacketDecoder:
    return hesai_decoder(config.model, path)


def _robosense(path: Path, config: LidarConfig) -> PacketDecoder:
    # its data packets do not say the return mode (the device-info packets do): the config does
    return robosense_decoder(config.model, path, dual_return=config.return_mode == "dual", rpm=60.0 * config.rate_hz)


VENDOR_LIDARS = {
    lidar.model: lidar
    for lidar in (
        *(VendorLidar(model, _velodyne, HOUR_NS) for model in VELODYNE_MODELS),  # microseconds past the hour
        # Hesai: the angle-correction CSV (the AT128: its binary correction file); stamps in UTC
        *(VendorLidar(model, _hesai, None, hesai_imu_samples if model == "hesai-pandar128e4x" else None)
          for model in HESAI_MODELS),
        *(VendorLidar(model, _robosense, None) for model in ROBOSENSE_MODELS),  # the angle CSV; UTC stamps
    )
}


def configured_decoder(config: LidarConfig, config_path: str | Path) -> PacketDecoder:
    """A decoder of the configured vendor sensor, from its calibration file (relative to the config file); a file
    that cannot be read or does not fit the model is a ConfigError naming it."""
    lidar = VENDOR_LIDARS.get(config.model)
    if lidar is None:
        raise ConfigError(f"{config_path}: sensors.lidar.model {config.model!r} has no vendor packet decoder")
    if not config.metadata_file:
        raise ConfigError(f"{config_path}: sensors.lidar.metadata_file is required for {config.model} (its "
                          f"calibration file)")
    path = resolve_path(config_path, config.metadata_file)
    try:
        return lidar.load_decoder(path, config)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{config_path}: sensors.lidar.metadata_file {str(path)!r}: {exc}") from None
