"""Ouster sensor metadata: parse the sensor's JSON (legacy and non-legacy layouts) into one typed
dataclass, and write the JSON of a simulated OS-128 that ouster-sdk accepts."""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from daemon.spine.config import ConfigError, resolve_path

if TYPE_CHECKING:
    from daemon.spine.config import LidarConfig


@dataclass
class OusterMetadata:
    """What a decoder needs to know about one Ouster sensor, in the sensor's own units."""

    prod_line: str  # e.g. "OS-1-128"
    prod_sn: str  # serial number, as printed on the unit
    firmware: str  # image_rev (or build_rev when image_rev is absent)
    init_id: int  # changes each time the sensor re-initialises
    lidar_mode: str  # e.g. "2048x10"
    udp_profile_lidar: str  # e.g. "LEGACY", "RNG19_RFL8_SIG16_NIR16" (see ouster_packet_layout)
    udp_profile_imu: str
    header_type: str  # "STANDARD" or "FUSA" (32-bit frame id header)
    columns_per_frame: int
    columns_per_packet: int
    pixels_per_column: int
    column_window: tuple[int, int]  # first and last measurement id sent, inclusive
    pixel_shift_by_row: np.ndarray  # (H,) int, columns to roll each row by to destagger
    beam_altitude_angles: np.ndarray  # (H,) degrees
    beam_azimuth_angles: np.ndarray  # (H,) degrees
    lidar_origin_to_beam_origin_mm: float
    beam_to_lidar_transform: np.ndarray  # (4, 4), translation in mm
    lidar_to_sensor_transform: np.ndarray  # (4, 4), translation in mm
    imu_to_sensor_transform: np.ndarray  # (4, 4), translation in mm
    udp_port_lidar: int
    udp_port_imu: int

    @property
    def fps(self) -> int:
        return int(self.lidar_mode.split("x")[1])

    @property
    def packets_per_frame(self) -> int:
        return -(-self.columns_per_frame // self.columns_per_packet)

    @property
    def frame_id_modulus(self) -> int:
        """Frame ids wrap at this value (16-bit, or 32-bit with the FuSa header)."""
        return 1 << 32 if self.header_type == "FUSA" else 1 << 16


MAX_PIXELS_PER_COLUMN = 1024  # beams (Ouster's are 16 to 128)
MAX_COLUMNS_PER_FRAME = 1 << 16  # Ouster's are 512 to 4096
_LIDAR_MODE = re.compile(r"^([1-9][0-9]{0,5})x([1-9][0-9]{0,3})$")


def _fail(name: str, what: str) -> ValueError:
    return ValueError(f"Ouster metadata: {name} {what}")


def _get(d: Any, *keys: str) -> Any:
    for i, key in enumerate(keys):
        if not isinstance(d, dict):
            raise _fail(".".join(keys[:i]) or "the document", f"must be an object, not {type(d).__name__}")
        if key not in d:
            raise ValueError(f"Ouster metadata: missing key {'.'.join(keys)!r}")
        d = d[key]
    return d


def _object(value: Any, name: str) -> dict:
    if not isinstance(value, dict):
        raise _fail(name, f"must be an object, not {type(value).__name__}")
    return value


def _int(value: Any, name: str, low: int, high: int) -> int:
    """An integer in [low, high] (JSON may write it as 16.0; a bool is not one)."""
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise _fail(name, f"must be an integer from {low} to {high}, not {value!r:.40}")
    return value


def _float(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise _fail(name, f"must be a finite number, not {value!r:.40}")
    return float(value)


def _array(values: Any, name: str, size: int, dtype: type = np.float64) -> np.ndarray:
    """A flat array of `size` finite numbers."""
    if not isinstance(values, list) or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                               for v in values):
        raise _fail(name, "must be a list of numbers")
    if len(values) != size:
        raise _fail(name, f"must have {size} values, has {len(values)}")
    try:
        array = np.asarray(values, dtype=np.float64)
    except OverflowError:
        raise _fail(name, "holds a number out of range") from None
    if not np.isfinite(array).all():
        raise _fail(name, "must hold finite numbers")
    if dtype is not np.float64:
        if (np.abs(array) > 2**31).any() or (array != np.round(array)).any():
            raise _fail(name, "must hold integers")
        array = array.astype(dtype)
    return array


def _matrix(values: Any, name: str) -> np.ndarray:
    return _array(values, name, 16).reshape(4, 4)


def _beam_to_lidar(origin_mm: float) -> np.ndarray:
    m = np.eye(4)
    m[0, 3] = origin_mm
    return m


def _document(source: str | bytes | dict | Path) -> dict:
    if isinstance(source, Path):
        source = source.read_bytes()
    if isinstance(source, str | bytes):
        try:
            source = json.loads(source)
        except RecursionError:
            raise ValueError("Ouster metadata: JSON nested too deeply") from None
        except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
            raise ValueError(f"Ouster metadata: not JSON ({exc})") from None
    return _object(source, "the document")


def parse_metadata(source: str | bytes | dict | Path) -> OusterMetadata:
    """Parse sensor metadata from JSON text, a decoded dict or a file path.

    Accepts both the legacy flat layout (firmware 2.x: "data_format", "beam_altitude_angles" at top
    level) and the non-legacy sectioned one ("lidar_data_format", "beam_intrinsics", ...). Raises
    ValueError naming the first missing or unusable key (of the wrong type, size or range), and nothing else."""
    d = _document(source)
    if "lidar_data_format" in d:
        fmt = _object(d["lidar_data_format"], "lidar_data_format")
        beams = _object(_get(d, "beam_intrinsics"), "beam_intrinsics")
        info = _object(d.get("sensor_info", {}), "sensor_info")
        config = _object(d.get("config_params", {}), "config_params")
        lidar_to_sensor = _get(d, "lidar_intrinsics", "lidar_to_sensor_transform")
        imu_to_sensor = _object(d.get("imu_intrinsics", {}), "imu_intrinsics").get("imu_to_sensor_transform")
        lidar_mode = config.get("lidar_mode") or f"{_get(fmt, 'columns_per_frame')}x{fmt.get('fps', 10)}"
        ports = (config.get("udp_port_lidar", 7502), config.get("udp_port_imu", 7503))
    else:
        fmt = _object(_get(d, "data_format"), "data_format")
        beams, info = d, d
        lidar_to_sensor = _get(d, "lidar_to_sensor_transform")
        imu_to_sensor = d.get("imu_to_sensor_transform")
        lidar_mode = _get(d, "lidar_mode")
        ports = (d.get("udp_port_lidar", 7502), d.get("udp_port_imu", 7503))

    profile = str(fmt.get("udp_profile_lidar", "LEGACY"))
    header_type = str(fmt.get("header_type") or ("FUSA" if profile.startswith("FUSA_") else "STANDARD"))
    h = _int(_get(fmt, "pixels_per_column"), "pixels_per_column", 1, MAX_PIXELS_PER_COLUMN)
    w = _int(_get(fmt, "columns_per_frame"), "columns_per_frame", 1, MAX_COLUMNS_PER_FRAME)
    columns_per_packet = _int(_get(fmt, "columns_per_packet"), "columns_per_packet", 1, w)
    if w % columns_per_packet:
        raise ValueError("Ouster metadata: columns_per_frame must be a multiple of columns_per_packet")
    if not isinstance(lidar_mode, str) or not _LIDAR_MODE.match(lidar_mode):
        raise _fail("lidar_mode", f"must be COLUMNSxFPS such as '1024x10', not {lidar_mode!r:.40}")
    window = fmt.get("column_window", [0, w - 1])
    if not isinstance(window, list) or len(window) != 2:
        raise _fail("column_window", "must be [first, last]")
    origin_mm = _float(_get(beams, "lidar_origin_to_beam_origin_mm"), "lidar_origin_to_beam_origin_mm")
    if "beam_to_lidar_transform" in beams:
        beam_to_lidar = _matrix(beams["beam_to_lidar_transform"], "beam_to_lidar_transform")
    else:
        beam_to_lidar = _beam_to_lidar(origin_mm)
    return OusterMetadata(
        prod_line=str(info.get("prod_line", "")),
        prod_sn=str(info.get("prod_sn", "")),
        firmware=str(info.get("image_rev") or info.get("build_rev", "")),
        init_id=_int(info.get("initialization_id", 0), "initialization_id", 0, 2**63 - 1),
        lidar_mode=lidar_mode,
        udp_profile_lidar=profile,
        udp_profile_imu=str(fmt.get("udp_profile_imu", "LEGACY")),
        header_type=header_type,
        columns_per_frame=w,
        columns_per_packet=columns_per_packet,
        pixels_per_column=h,
        column_window=(_int(window[0], "column_window", 0, w - 1), _int(window[1], "column_window", 0, w - 1)),
        pixel_shift_by_row=_array(_get(fmt, "pixel_shift_by_row"), "pixel_shift_by_row", h, np.int64),
        beam_altitude_angles=_array(_get(beams, "beam_altitude_angles"), "beam_altitude_angles", h),
        beam_azimuth_angles=_array(_get(beams, "beam_azimuth_angles"), "beam_azimuth_angles", h),
        lidar_origin_to_beam_origin_mm=origin_mm,
        beam_to_lidar_transform=beam_to_lidar,
        lidar_to_sensor_transform=_matrix(lidar_to_sensor, "lidar_to_sensor_transform"),
        imu_to_sensor_transform=np.eye(4) if imu_to_sensor is None else _matrix(imu_to_sensor,
                                                                               "imu_to_sensor_transform"),
        udp_port_lidar=_int(ports[0], "udp_port_lidar", 0, 65535),
        udp_port_imu=_int(ports[1], "udp_port_imu", 0, 65535),
    )


def simulated_os128_metadata(
    columns_per_frame: int = 2048,
    fps: int = 10,
    udp_profile_lidar: str = "LEGACY",
    prod_sn: str = "122000000128",
    init_id: int = 1280001,
) -> OusterMetadata:
    """Metadata of a nominal OS-1-128: uniform 45 degree vertical field of view, the four-column
    azimuth stagger of real units, pixel shifts as firmware 3.x computes them."""
    if columns_per_frame not in (512, 1024, 2048, 4096):
        raise ValueError(f"columns_per_frame must be 512, 1024, 2048 or 4096, not {columns_per_frame}")
    azimuth = np.tile([4.2, 1.4, -1.4, -4.2], 32)
    lidar_to_sensor = np.diag([-1.0, -1.0, 1.0, 1.0])
    lidar_to_sensor[2, 3] = 36.18
    origin_mm = 15.806
    return OusterMetadata(
        prod_line="OS-1-128",
        prod_sn=prod_sn,
        firmware="ousteros-image-prod-bootes-v3.1.0+roadlog.simulated",
        init_id=init_id,
        lidar_mode=f"{columns_per_frame}x{fps}",
        udp_profile_lidar=udp_profile_lidar,
        udp_profile_imu="LEGACY",
        header_type="FUSA" if udp_profile_lidar.startswith("FUSA_") else "STANDARD",
        columns_per_frame=columns_per_frame,
        columns_per_packet=16,
        pixels_per_column=128,
        column_window=(0, columns_per_frame - 1),
        pixel_shift_by_row=np.round(azimuth * columns_per_frame / 360.0).astype(np.int64),
        beam_altitude_angles=np.linspace(22.5, -22.5, 128),
        beam_azimuth_angles=azimuth,
        lidar_origin_to_beam_origin_mm=origin_mm,
        beam_to_lidar_transform=_beam_to_lidar(origin_mm),
        lidar_to_sensor_transform=lidar_to_sensor,
        imu_to_sensor_transform=np.eye(4),
        udp_port_lidar=7502,
        udp_port_imu=7503,
    )


def _flat(m: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(m, dtype=np.float64).ravel()]


def metadata_to_json(meta: OusterMetadata) -> str:
    """The non-legacy (firmware 3.x) metadata JSON for `meta`; `parse_metadata` reads it back and
    ouster-sdk's SensorInfo accepts it."""
    data_format = {
        "column_window": list(meta.column_window),
        "columns_per_frame": meta.columns_per_frame,
        "columns_per_packet": meta.columns_per_packet,
        "fps": meta.fps,
        "header_type": meta.header_type,
        "pixel_shift_by_row": [int(v) for v in meta.pixel_shift_by_row],
        "pixels_per_column": meta.pixels_per_column,
        "udp_profile_imu": meta.udp_profile_imu,
        "udp_profile_lidar": meta.udp_profile_lidar,
    }
    doc = {
        "beam_intrinsics": {
            "beam_altitude_angles": [float(v) for v in meta.beam_altitude_angles],
            "beam_azimuth_angles": [float(v) for v in meta.beam_azimuth_angles],
            "beam_to_lidar_transform": _flat(meta.beam_to_lidar_transform),
            "lidar_origin_to_beam_origin_mm": meta.lidar_origin_to_beam_origin_mm,
        },
        "calibration_status": {},
        "config_params": {
            "columns_per_packet": meta.columns_per_packet,
            "lidar_mode": meta.lidar_mode,
            "udp_port_imu": meta.udp_port_imu,
            "udp_port_lidar": meta.udp_port_lidar,
            "udp_profile_imu": meta.udp_profile_imu,
            "udp_profile_lidar": meta.udp_profile_lidar,
        },
        "imu_intrinsics": {"imu_to_sensor_transform": _flat(meta.imu_to_sensor_transform)},
        "lidar_data_format": data_format,
        "lidar_intrinsics": {"lidar_to_sensor_transform": _flat(meta.lidar_to_sensor_transform)},
        "sensor_info": {
            "build_rev": meta.firmware,
            "image_rev": meta.firmware,
            "initialization_id": meta.init_id,
            "prod_line": meta.prod_line,
            "prod_pn": "",
            "prod_sn": meta.prod_sn,
            "status": "RUNNING",
        },
    }
    return json.dumps(doc, indent=2)


def imu_port(config: LidarConfig, metadata: OusterMetadata) -> int | None:
    """Where the driver listens for the sensor's IMU packets: the config's port, else the metadata's; None
    when the config sets 0 (IMU off)."""
    port = metadata.udp_port_imu if config.imu_port is None else config.imu_port
    return port or None


def configured_metadata(config: LidarConfig, config_path: str | Path) -> OusterMetadata:
    """The metadata of the configured sensor (`metadata_file`, relative to the config file); a file that cannot be
    read or parsed is a ConfigError naming it, as is a point-cloud Lidar (it has none: its scans come decoded)."""
    if config.metadata_file is None:
        raise ConfigError(f"{config_path}: sensors.lidar.model {config.model!r} has no Ouster metadata_file: its scans "
                          f"come decoded, not as Ouster packets")
    path = resolve_path(config_path, config.metadata_file)
    try:
        return parse_metadata(path)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{config_path}: sensors.lidar.metadata_file {str(path)!r}: {exc}") from None
