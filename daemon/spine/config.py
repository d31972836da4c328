"""The car's configuration: one validated schema (sensors, bus, recorder, mapper, status server).

Conventions used everywhere:
- Vehicle frame: x forward, y left, z up; origin at the vehicle reference point (the pose-fusion output),
  which sits `vehicle.reference_height_m` above the ground.
- Extrinsics give a sensor's pose in the vehicle frame: translation (m) and roll/pitch/yaw (degrees,
  applied as R = Rz(yaw) @ Ry(pitch) @ Rx(roll)).
- Camera axes follow OpenCV: x right, y down, z forward (optical axis).
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Literal, ParamSpec

import numpy as np
import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from daemon.spine.config_model import StrictModel
from daemon.spine.mapper_config import MapperConfig
from daemon.spine.process_logging import error_line
from daemon.spine.yaml_document import UnusableYaml, load_yaml

P = ParamSpec("P")


class ConfigError(Exception):
    """A configuration file that cannot be used; the message names the file, key path and expectation."""


class Extrinsics(StrictModel):
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def rotation_matrix(self) -> np.ndarray:
        r, p, y = np.deg2rad(self.rotation_rpy_deg)
        rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
        ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
        rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
        return rz @ ry @ rx

    def matrix(self) -> np.ndarray:
        """4x4 transform from the sensor frame to the vehicle frame."""
        t = np.eye(4)
        t[:3, :3] = self.rotation_matrix()
        t[:3, 3] = self.translation_m
        return t


class CameraIntrinsics(StrictModel):
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


class CameraPhotometry(StrictModel):
    """The simulator's photometric response of a camera (ignored by real backends)."""

    gain: float = Field(1.0, gt=0)
    gamma: float = Field(1.0, gt=0)
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    saturation: float = Field(1.0, ge=0)
    vignetting: float = Field(0.0, ge=0, le=1)
    noise_sigma: float = Field(1.0, ge=0)


# The encodings each camera backend can deliver: host-side encoders (frame_encoding) for opencv and the simulator's
# playback, the device's own for an OAK; a recorded camera (frames only in logs, e.g. an imported dataset) any.
BACKEND_ENCODINGS = {
    "sim": ("jpeg", "png", "raw", "mono8"),
    "opencv": ("jpeg", "png", "raw", "mono8"),
    "depthai": ("jpeg", "h264", "h265", "raw"),
    "recorded": ("jpeg", "png", "h264", "h265", "raw", "mono8"),
}


class CameraConfig(StrictModel):
    name: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    backend: Literal["sim", "opencv", "depthai", "recorded"]  # recorded: no live driver (frames come from logs)
    device: str = ""  # V4L2 path, GStreamer pipeline, or OAK serial number
    model: Literal["pinhole"] = "pinhole"
    width: int = Field(gt=0, le=8192)
    height: int = Field(gt=0, le=8192)
    rate_hz: float = Field(gt=0, le=120)
    intrinsics: CameraIntrinsics
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)  # k1 k2 p1 p2 k3
    extrinsics: Extrinsics
    encoding: Literal["jpeg", "png", "h264", "h265", "raw", "mono8"] = "jpeg"
    jpeg_quality: int = Field(90, ge=1, le=100)
    photometry: CameraPhotometry = CameraPhotometry()
    loop: bool = False  # sim backend only: play the drive log again and again, an endless drive (soaks)

    @model_validator(mode="after")
    def _principal_point_inside(self) -> CameraConfig:
        if not (0 <= self.intrinsics.cx <= self.width and 0 <= self.intrinsics.cy <= self.height):
            raise ValueError("intrinsics cx/cy must lie inside the image (0..width, 0..height)")
        if self.encoding not in BACKEND_ENCODINGS[self.backend]:
            raise ValueError(f"the {self.backend} backend delivers {', '.join(BACKEND_ENCODINGS[self.backend])}, "
                             f"not {self.encoding}")
        if self.loop and self.backend != "sim":
            raise ValueError("loop: only a sim camera plays its drive again and again")
        return self


POINT_CLOUD_LIDAR = "point-cloud"  # a Lidar model whose scans arrive already decoded (messages.PointCloud)
OUSTER_LIDARS = ("ouster-os-128", "ouster-os-32")
# the models decoded from packets by a vendor decoder (drivers/lidar/lidar_models.py; a test keeps the two equal)
VENDOR_LIDARS = ("velodyne-vlp16", "velodyne-vlp32c", "velodyne-vls128", "velodyne-hdl64e", "hesai-pandar40p",
                 "hesai-pandar64", "hesai-pandarqt128", "hesai-pandarxt32", "hesai-pandar128e4x", "hesai-pandarat128",
                 "robosense-helios16p", "robosense-ruby128")
LIDAR_DEFAULT_PORTS = {"ouster": 7502, "velodyne": 2368, "hesai": 2368, "robosense": 6699}  # by vendor, as shipped
LidarModel = Literal[(*OUSTER_LIDARS, *VENDOR_LIDARS, POINT_CLOUD_LIDAR)]


class LidarConfig(StrictModel):
    # exactly the models the driver and the mapper decode: Ouster packets, another vendor's packets
    # (VENDOR_LIDARS), or scans already decoded into points (POINT_CLOUD_LIDAR: an imported dataset, a ROS bag,
    # another system's driver; they come only in logs, there is no live driver for them)
    model: LidarModel
    bind_address: str = "0.0.0.0"
    port: int = Field(7502, ge=1, le=65535)  # when left out: the vendor's factory port (LIDAR_DEFAULT_PORTS)
    imu_port: int | None = Field(None, ge=0, le=65535)  # Ouster: None: the metadata's udp_port_imu; 0: IMU off
    # the sensor's own calibration, required for every model but point-cloud: the Ouster's metadata JSON, the
    # Velodyne calibration YAML (velodyne_pointcloud's layout), the Hesai or RoboSense angle-correction CSV
    metadata_file: str | None = None
    columns_per_frame: Literal[512, 1024, 2048] = 1024  # Ouster only
    rate_hz: Literal[5, 10, 15, 20] = 10  # rotations per second (Ouster: 10 or 20)
    receive_buffer_bytes: int = Field(64 * 1024 * 1024, ge=1 << 16)
    return_mode: Literal["single", "dual"] = "single"  # RoboSense only: as set on the sensor (its data packets
    # do not say); the other vendors' packets do
    extrinsics: Extrinsics

    @property
    def point_clouds(self) -> bool:
        """Whether its scans arrive as decoded point clouds (`lidar/points`) instead of packets."""
        return self.model == POINT_CLOUD_LIDAR

    @property
    def vendor_packets(self) -> bool:
        """Whether its packets are decoded by a vendor decoder (not Ouster's)."""
        return self.model in VENDOR_LIDARS

    @model_validator(mode="before")
    @classmethod
    def _vendor_port(cls, data: object) -> object:
        vendor = str(data.get("model")).split("-")[0] if isinstance(data, dict) else None
        if isinstance(data, dict) and "port" not in data and vendor in LIDAR_DEFAULT_PORTS:
            return {**data, "port": LIDAR_DEFAULT_PORTS[vendor]}
        return data

    @model_validator(mode="after")
    def _packets_need_metadata(self) -> LidarConfig:
        if not self.point_clouds and not self.metadata_file:
            raise ValueError(f"metadata_file is required for model {self.model} (the sensor's calibration file, "
                             f"which its packets are decoded with); only model {POINT_CLOUD_LIDAR} goes without")
        if self.model in OUSTER_LIDARS and self.rate_hz not in (10, 20):
            raise ValueError(f"rate_hz: an Ouster turns at 10 or 20 Hz, not {self.rate_hz}")
        return self


class GnssConfig(StrictModel):
    port: str
    baud: int = Field(115200, gt=0)
    protocol: Literal["nmea", "ubx", "nmea+ubx"] = "nmea+ubx"
    rate_hz: float = Field(10.0, gt=0)
    imu_rate_hz: float = Field(100.0, gt=0)
    antenna_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # antenna in the vehicle frame
    imu_extrinsics: Extrinsics = Extrinsics()
    # The IMU accelerometer's turn-on bias, 1-sigma per axis (m/s^2), from its datasheet: the pose fusion's prior.
    # On a drive with few heading changes the roll and the sideways bias are one unknown (both tilt the measured
    # gravity), so this prior bounds the fused roll error (about sigma / g rad). 0.2 (20 mg) when unknown.
    imu_accel_bias_sigma_mps2: float = Field(0.2, gt=0, le=2.0)


class CanSignals(StrictModel):
    """Signal names as MESSAGE.SIGNAL in the DBC."""

    wheel_speed_fl: str
    wheel_speed_fr: str
    wheel_speed_rl: str
    wheel_speed_rr: str
    yaw_rate: str | None = None
    speed_unit: Literal["m/s", "km/h", "rad/s"] = "km/h"  # rad/s: wheel angular rate, times wheel_radius_m
    wheel_radius_m: float = Field(0.33, gt=0)
    yaw_rate_unit: Literal["rad/s", "deg/s"] = "deg/s"

    @field_validator("wheel_speed_fl", "wheel_speed_fr", "wheel_speed_rl", "wheel_speed_rr", "yaw_rate")
    @classmethod
    def _dotted(cls, v: str | None) -> str | None:
        if v is not None and (v.count(".") != 1 or not all(v.split("."))):
            raise ValueError("must be MESSAGE.SIGNAL")
        return v


class CanConfig(StrictModel):
    interface: str = "socketcan"  # any python-can interface: socketcan, virtual, udp_multicast, slcan, ...
    channel: str = "can0"
    bitrate: int | None = Field(500000, gt=0)
    dbc_file: str
    signals: CanSignals
    options: dict[str, str | int | float | bool] = {}  # extra python-can bus arguments (e.g. udp_multicast port)


class SensorsConfig(StrictModel):
    cameras: list[CameraConfig] = Field(min_length=1)
    lidar: LidarConfig | None = None
    gnss: GnssConfig | None = None
    can: CanConfig | None = None

    @field_validator("cameras")
    @classmethod
    def _unique_names(cls, cams: list[CameraConfig]) -> list[CameraConfig]:
        names = [c.name for c in cams]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        return cams


class VehicleConfig(StrictModel):
    name: str = "car"
    reference_height_m: float = Field(0.0, ge=0, le=5)  # reference point height above the ground
    wheel_base_m: float = Field(2.8, gt=0)
    track_width_m: float = Field(1.6, gt=0)
    rear_axle_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rear axle centre in the vehicle frame


class BusConfig(StrictModel):
    shm_prefix: str = Field("roadlog", pattern=r"^[A-Za-z0-9_]+$")
    ring_bytes: dict[str, int] = {}  # per-topic overrides of the topic table's ring size


Seconds = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class RecorderConfig(StrictModel):
    output_dir: str = "logs"
    # a segment closes once its messages span this much log time (their own time, not the wall clock: a replay at any
    # rate is cut at the same messages; daemon/processes/segment_clock.py), or at segment_bytes, whichever comes first
    segment_seconds: float = Field(60.0, gt=0)
    segment_bytes: int = Field(2 * 1024**3, gt=0)
    min_free_gib: float = Field(5.0, ge=0)
    min_free_pct: float = Field(5.0, ge=0, le=100)
    # the newest segments holding at least this many seconds of drive are never deleted to make room
    keep_newest_s: float = Field(300.0, ge=0, allow_inf_nan=False)
    # after a deletion whose space another program took, no deletion for the first of these; twice as long after each
    # further one in a row, up to the second (daemon/processes/disk_policy.py)
    deletion_hold_off_s: tuple[Seconds, Seconds] = (2.0, 300.0)
    compression: Literal["zstd", "lz4", "none"] = "lz4"
    # longest a message is held to be written in log-time order (a ring the recorder is behind on); 0: as read
    reorder_window_s: float = Field(5.0, ge=0, le=60)
    # for viewing (Foxglove's 3D panel), beside the lossless record: a Lidar scan decoded into points at most this
    # often (`lidar/view`, foxglove.PointCloud; never read by the mapper); at most the Lidar's rate_hz; 0: none
    point_cloud_view_hz: float = Field(2.0, ge=0, le=20, allow_inf_nan=False)
    # the vehicle pose fused live from GNSS, IMU and wheel speeds this often (`vehicle/pose` as foxglove.PoseInFrame
    # and `tf` as foxglove.FrameTransform, map -> vehicle); 0: none
    pose_hz: float = Field(10.0, ge=0, le=50, allow_inf_nan=False)

    @field_validator("deletion_hold_off_s")
    @classmethod
    def _first_hold_off_is_the_shortest(cls, value: tuple[float, float]) -> tuple[float, float]:
        if value[0] > value[1]:
            raise ValueError(f"deletion_hold_off_s: the first hold-off ({value[0]} s) is longer than the longest "
                             f"({value[1]} s)")
        return value


class StatusConfig(StrictModel):
    bind_address: str = "127.0.0.1"
    port: int = Field(8088, ge=0, le=65535)


class CarConfig(StrictModel):
    vehicle: VehicleConfig = VehicleConfig()
    sensors: SensorsConfig
    bus: BusConfig = BusConfig()
    recorder: RecorderConfig = RecorderConfig()
    mapper: MapperConfig = MapperConfig()
    status: StatusConfig = StatusConfig()

    @model_validator(mode="after")
    def _view_within_the_lidar_rate(self) -> CarConfig:
        lidar, view_hz = self.sensors.lidar, self.recorder.point_cloud_view_hz
        if lidar is not None and not lidar.point_clouds and view_hz > lidar.rate_hz:
            raise ValueError(f"recorder.point_cloud_view_hz {view_hz:g} is above sensors.lidar.rate_hz "
                             f"{lidar.rate_hz}: the Lidar gives only that many scans a second")
        return self

    def camera(self, name: str) -> CameraConfig:
        for cam in self.sensors.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"no camera named {name!r}")


def _describe(error: dict) -> str:
    path = ".".join(str(p) for p in error["loc"]) or "(top level)"
    msg = error["msg"]
    if error["type"] == "extra_forbidden":
        msg = "unknown key (not part of the schema)"
    elif error["type"] == "missing":
        msg = "required key is missing"
    got = "" if error["type"] == "missing" else f" (got {error.get('input')!r:.80})"
    return f"{path}: {msg}{got}"


def parse_config(data: object, source: str = "<config>") -> CarConfig:
    """Validate an already-parsed config mapping; raise ConfigError naming the source and key path."""
    try:
        return CarConfig.model_validate(data)
    except ValidationError as exc:
        lines = [_describe(e) for e in exc.errors()]
        raise ConfigError(f"{source}: invalid configuration:\n  " + "\n  ".join(lines)) from None


def resolve_path(config_file: str | Path, value: str) -> Path:
    """A path from the config, relative paths taken from the config file's folder."""
    p = Path(value).expanduser()
    return p if p.is_absolute() else (Path(config_file).resolve().parent / p)


def data_dir(config: CarConfig, override: str | Path | None = None) -> Path:
    """The folder for log segments and maps, absolute: the override, else recorder.output_dir. A relative one is taken
    from the current working directory (systemd's WorkingDirectory), as a replay's `--output-dir` is: an output
    never lands beside the config (configs/logs for configs/sim.yaml); the files a config names as inputs
    (calibrations, the DBC) are the ones taken from its folder (`resolve_path`)."""
    return (Path(override) if override else Path(config.recorder.output_dir)).expanduser().absolute()


def load_config(path: str | Path) -> CarConfig:
    """Read and validate a YAML car config; any problem raises ConfigError with one clear message."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file: {exc.strerror}") from None
    try:
        data = load_yaml(raw)
    except UnusableYaml as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: (top level): expected a mapping of sections, got {type(data).__name__}")
    return parse_config(data, str(path))


EXIT_CONFIG_ERROR = 2  # a process's exit status for "this config cannot work": the supervisor does not retry


def reports_config_errors(main: Callable[P, int]) -> Callable[P, int]:
    """The one exit rule for configuration errors, decorating every process's main(): a ConfigError raised while
    it runs (an unusable config, a file it names that it needs, a platform the bus cannot run on) becomes one
    `error: ...` line on stderr (at error priority under the journal) and exit status EXIT_CONFIG_ERROR, which the
    supervisor does not retry."""

    @functools.wraps(main)
    def reporting(*args: P.args, **kwargs: P.kwargs) -> int:
        try:
            return main(*args, **kwargs)
        except ConfigError as exc:
            print(error_line(str(exc)), file=sys.stderr)
            return EXIT_CONFIG_ERROR

    return reporting


def config_to_yaml(config: CarConfig) -> str:
    """The resolved config as YAML (saved beside every output and in every log segment)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
