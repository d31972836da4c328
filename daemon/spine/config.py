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
from typing import Literal, ParamSpec

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from daemon.spine.process_logging import error_line
from daemon.spine.yaml_document import UnusableYaml, load_yaml

P = ParamSpec("P")


class ConfigError(Exception):
    """A configuration file that cannot be used; the message names the file, key path and expectation."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Extrinsics(_Strict):
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


class CameraIntrinsics(_Strict):
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


class CameraPhotometry(_Strict):
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


class CameraConfig(_Strict):
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

    @model_validator(mode="after")
    def _principal_point_inside(self) -> CameraConfig:
        if not (0 <= self.intrinsics.cx <= self.width and 0 <= self.intrinsics.cy <= self.height):
            raise ValueError("intrinsics cx/cy must lie inside the image (0..width, 0..height)")
        if self.encoding not in BACKEND_ENCODINGS[self.backend]:
            raise ValueError(f"the {self.backend} backend delivers {', '.join(BACKEND_ENCODINGS[self.backend])}, "
                             f"not {self.encoding}")
        return self


POINT_CLOUD_LIDAR = "point-cloud"  # a Lidar model whose scans arrive already decoded (messages.PointCloud)


class LidarConfig(_Strict):
    # exactly the models the driver and the mapper decode: Ouster packets, or scans already decoded into points
    # (POINT_CLOUD_LIDAR: an imported dataset, a ROS bag, another system's driver; they come only in logs, there is
    # no live driver for them)
    model: Literal["ouster-os-128", "ouster-os-32", "point-cloud"]
    bind_address: str = "0.0.0.0"
    port: int = Field(7502, ge=1, le=65535)
    imu_port: int | None = Field(None, ge=0, le=65535)  # None: the metadata's udp_port_imu; 0: IMU off
    metadata_file: str | None = None  # the Ouster's own calibration JSON (required for the Ouster models)
    columns_per_frame: Literal[512, 1024, 2048] = 1024
    rate_hz: Literal[10, 20] = 10
    receive_buffer_bytes: int = Field(64 * 1024 * 1024, ge=1 << 16)
    extrinsics: Extrinsics

    @property
    def point_clouds(self) -> bool:
        """Whether its scans arrive as decoded point clouds (`lidar/points`) instead of Ouster packets."""
        return self.model == POINT_CLOUD_LIDAR

    @model_validator(mode="after")
    def _packets_need_metadata(self) -> LidarConfig:
        if not self.point_clouds and not self.metadata_file:
            raise ValueError(f"metadata_file is required for model {self.model} (the sensor's metadata JSON, "
                             f"which its packets are decoded with); only model {POINT_CLOUD_LIDAR} goes without")
        return self


class GnssConfig(_Strict):
    port: str
    baud: int = Field(115200, gt=0)
    protocol: Literal["nmea", "ubx", "nmea+ubx"] = "nmea+ubx"
    rate_hz: float = Field(10.0, gt=0)
    imu_rate_hz: float = Field(100.0, gt=0)
    antenna_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # antenna in the vehicle frame
    imu_extrinsics: Extrinsics = Extrinsics()


class CanSignals(_Strict):
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


class CanConfig(_Strict):
    interface: str = "socketcan"  # any python-can interface: socketcan, virtual, udp_multicast, slcan, ...
    channel: str = "can0"
    bitrate: int | None = Field(500000, gt=0)
    dbc_file: str
    signals: CanSignals
    options: dict[str, str | int | float | bool] = {}  # extra python-can bus arguments (e.g. udp_multicast port)


class SensorsConfig(_Strict):
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


class VehicleConfig(_Strict):
    name: str = "car"
    reference_height_m: float = Field(0.0, ge=0, le=5)  # reference point height above the ground
    wheel_base_m: float = Field(2.8, gt=0)
    track_width_m: float = Field(1.6, gt=0)
    rear_axle_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rear axle centre in the vehicle frame


class BusConfig(_Strict):
    shm_prefix: str = Field("roadlog", pattern=r"^[A-Za-z0-9_]+$")
    ring_bytes: dict[str, int] = {}  # per-topic overrides of the topic table's ring size


class RecorderConfig(_Strict):
    output_dir: str = "logs"
    segment_seconds: float = Field(60.0, gt=0)
    segment_bytes: int = Field(2 * 1024**3, gt=0)
    min_free_gib: float = Field(5.0, ge=0)
    min_free_pct: float = Field(5.0, ge=0, le=100)
    compression: Literal["zstd", "lz4", "none"] = "lz4"


class LearningRates(_Strict):
    """Adam learning rates of the faithful fit, one optimiser per parameter group."""

    elevation_mlp: float = Field(0.01, gt=0)  # the elevation MLP's weights
    colour_mlps: float = Field(0.005, gt=0)  # the per-camera colour decoders' weights
    semantics: float = Field(0.1, gt=0)  # the per-vertex semantic logits (row-sparse Adam)
    colour_codes: float = Field(0.005, gt=0)  # the per-vertex colour codes (row-sparse Adam)


class LossWeights(_Strict):
    """Weights of the faithful fit's four losses in its total."""

    rgb: float = Field(1.0, ge=0)  # L1 colour of the rendered pixels against the images
    semantics: float = Field(1.0, ge=0)  # cross-entropy of the rendered semantics against the masks
    elevation: float = Field(1.0, ge=0)  # L1 of the vertex heights against the Lidar ground points under them
    smoothness: float = Field(1.0, ge=0)  # L1 of the height differences between neighbouring vertices


class LiveViewConfig(_Strict):
    """The mapper's optional Foxglove WebSocket live view of the growing map (mapping.live.live_view)."""

    enabled: bool = False
    bind_address: str = "127.0.0.1"
    port: int = Field(8765, ge=0, le=65535)  # 0: any free port


MaskClassName = Literal["road", "lane_marking", "curb", "manhole", "background", "obstacle"]


class SegmentationConfig(_Strict):
    """Where the mapper's semantic masks come from (mapping.inputs.segmentation): `log`, the masks recorded beside
    the frames (the simulator's, or an upstream segmenter's); `onnx`, a semantic-segmentation model run on
    each keyframe with onnxruntime. The model takes one RGB image (1, 3, H, W) float32, scaled to [0, 1]
    then normalised by `mean` and `std`, and gives (1, C, H', W') class scores or (1, H', W') class ids;
    `class_map` names the map class of each model class id (ids it leaves out are unlabelled: not used)."""

    provider: Literal["log", "onnx"] = "log"
    model: str | None = None  # the .onnx file, relative to the config file
    class_map: dict[int, MaskClassName] = {}
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    input_size: tuple[int, int] | None = None  # (width, height) the image is resized to; None: the model's
    # own fixed input size, else the image's
    threads: int = Field(1, ge=1)  # onnxruntime intra-op threads

    @model_validator(mode="after")
    def _onnx_needs_a_model(self) -> SegmentationConfig:
        if self.provider == "onnx" and (not self.model or not self.class_map):
            raise ValueError("provider onnx needs `model` (an .onnx file) and `class_map` (model class id -> "
                             "map class name)")
        if any(v <= 0 for v in self.std):
            raise ValueError("std must be positive")
        return self


class MeshConfig(_Strict):
    """The road mesh (mapping.method.road_mesh): equilateral triangles cut to a corridor around the trajectory."""

    side_m: float = Field(0.1, gt=0, le=2)  # triangle side (m): the map's resolution, and the BEV rasters' cell
    corridor_half_width_m: float = Field(15.0, gt=0)  # the mesh reaches this far (m) either side of the
    # trajectory; the Lidar ground points are kept within the same corridor


class WindowsConfig(_Strict):
    """The stretch of road around a point of the trajectory that the model spans (the paper's 80 m + 80 m)."""

    before_m: float = Field(80.0, gt=0)  # metres of drive behind the point: the faithful fit's step window, the
    # evaluation's view window (up to 10 m behind a camera) and the live worker's window start
    after_m: float = Field(80.0, gt=0)  # metres ahead of it; before_m + after_m also scales the elevation
    # MLP's positional encoding, and the live worker's windows are centred every (before_m + after_m) / 2


class ModelConfig(_Strict):
    """The EMIE-MAP model both fits train (mapping.method.road_map)."""

    colour_code_dim: int = Field(32, gt=0)  # length of each vertex's colour code
    positional_encoding_dim: int = Field(22, gt=1)  # sin/cos features of x, y fed to the elevation MLP
    elevation_mlp_layers: int = Field(8, ge=1)  # hidden layers of the elevation MLP
    elevation_mlp_width: int = Field(128, ge=1)  # units per hidden layer of the elevation MLP
    colour_mlp_layers: int = Field(2, ge=1)  # layers of each camera's colour decoder
    colour_mlp_width: int = Field(16, ge=1)  # units per hidden layer of each colour decoder
    seed: int = 0  # seeds torch and numpy for the initial weights and the fits' sampling (the live worker
    # derives one per window from it)


class InputsConfig(_Strict):
    """Which camera frames and Lidar scans of a drive the fits are given (mapping.inputs, mapping.live)."""

    keyframe_spacing_m: float = Field(1.0, ge=0)  # per camera, a frame each time the vehicle has moved this
    # far (m) since the last one kept; 0: every frame
    lidar_every_n_scans: int = Field(2, ge=1)  # Lidar scans used: every n-th (a scan: one frame id's packets)


class FastFitConfig(_Strict):
    """The fast fit (the default; mapping.fits.fast_fit): the model fitted to what the keyframes saw at each
    vertex: elevation MLP on a lattice against the Lidar, the Lidar detail, label frequencies, colour encoder."""

    elevation_lattice_m: float = Field(1.0, ge=0)  # spacing (m) of the lattice the residual elevation MLP is
    # evaluated on and fitted at (interpolated between its nodes); 0: at every vertex. The Lidar detail carries
    # what is finer than the lattice
    elevation_epochs: float = Field(5.0, gt=0)  # passes over the Lidar lattice nodes of the elevation fit ...
    elevation_min_steps: int = Field(150, ge=1)  # ... but at least this many Adam steps (short drives)
    elevation_batch: int = Field(512, ge=1)  # lattice nodes per elevation step ...
    elevation_smooth_pairs: int = Field(128, ge=1)  # ... and neighbour pairs per step for the smoothness term
    elevation_lr: float = Field(0.01, gt=0)  # the elevation fit's Adam learning rate at its start (cosine decay)
    elevation_loss_weight: float = Field(1.0, ge=0)  # weight of the L1 Lidar height loss in the elevation fit
    smoothness_loss_weight: float = Field(1.0, ge=0)  # weight of the neighbour smoothness loss in it
    lidar_detail_passes: int = Field(8, ge=0)  # Jacobi passes of the Lidar detail (mapping.fits.lidar_detail),
    # the per-vertex height the smooth MLP cannot hold; 0: no detail
    lidar_detail_prior: float = Field(0.03, ge=0)  # points' worth of zero detail at each vertex (few points:
    # the vertex keeps the smooth surface)
    behind_m: float = Field(3.0, ge=0)  # a keyframe observes the vertices from this far (m) behind its
    # trajectory point ...
    ahead_m: float = Field(12.0, gt=0)  # ... to this far (m) ahead: farther views blur
    label_sharp_m: float | None = Field(0.01, gt=0)  # a pixel's label counts fully where the pixel covers at
    # most this much ground (m) along the line of sight, in proportion beyond (far views count less;
    # mapping.fits.vertex_observations.label_weights); None: every label counts 1
    colour_encoder_steps: int = Field(200, ge=1)  # steps of the joint colour encoder / decoder fit
    colour_batch: int = Field(4096, ge=1)  # vertices sampled per colour step
    colour_decoder_lr: float = Field(0.005, gt=0)  # Adam learning rate of the per-camera colour decoders
    colour_encoder_lr: float = Field(0.01, gt=0)  # Adam learning rate of the colour encoder (the codes' source)


class MasklessConfig(_Strict):
    """Keyframes without semantics (no mask, no segmentation model; mapping.fits.lidar_occlusion): a view's pixel
    is not used where the Lidar scan nearest in time saw something standing on the road (a car, a person, a wall)
    between the camera and the surface, as a mask's obstacle pixels are not."""

    lidar_occlusion: bool = True  # False: every pixel of such a view counts (cars in view reach the colours)
    standing_min_m: float = Field(0.4, gt=0)  # a Lidar point stands on the road from this height (m) above the
    # trajectory's ground (curbs, the crown and sidewalks are lower) ...
    standing_max_m: float = Field(3.0, gt=0)  # ... up to this one (higher: branches, signs; they hide little)
    cell_px: int = Field(8, ge=1)  # the test's image cells (px): a standing point hides the surface behind it in
    # its cell, the cells either side and every cell below (it stands on the ground)
    margin_m: float = Field(0.5, ge=0)  # a surface point is hidden when a standing point is this much nearer (m)
    max_gap_s: float = Field(0.25, gt=0)  # a view with no Lidar scan this close in time keeps every pixel (counted)

    @model_validator(mode="after")
    def _heights_in_order(self) -> MasklessConfig:
        if self.standing_max_m <= self.standing_min_m:
            raise ValueError("standing_max_m must be above standing_min_m")
        return self


class FaithfulFitConfig(_Strict):
    """The paper-faithful fit (`roadlog reconstruct --faithful`; mapping.fits.faithful_fit): every pixel of every
    batch image rendered against the whole window, each step."""

    learning_rates: LearningRates = LearningRates()
    loss_weights: LossWeights = LossWeights()
    epochs: int = Field(5, ge=1)  # passes over the training keyframes
    batch_size: int = Field(8, ge=1)  # adjacent keyframes (along the trajectory) per step


class RuntimeConfig(_Strict):
    """Threads of the mapper's pools and of torch. They change the speed only: the sums that split over threads
    split the same way whatever their timing, but their count is part of the order of the float sums."""

    torch_threads_fast_fit: int = Field(1, ge=1)  # torch intra-op threads of the fast fit and its evaluation
    # (its MLPs are small: more threads spin against each other)
    torch_threads_faithful_fit: int = Field(2, ge=1)  # torch intra-op threads of the faithful fit
    observe_threads: int = Field(2, ge=1)  # threads projecting the keyframes onto the vertices (fast fit)
    lidar_ground_threads: int = Field(2, ge=1)  # threads extracting the Lidar ground, scan by scan
    lidar_detail_threads: int = Field(2, ge=1)  # threads (and parts of the point sums) of the Lidar detail
    evaluation_threads: int = Field(2, ge=1)  # threads rendering and scoring the evaluation's views
    raster_threads: int = Field(2, ge=1)  # threads filling the bird's-eye rasters (blocks of rows)


class MapperConfig(_Strict):
    """The road-surface mapper (the live worker and `roadlog reconstruct`)."""

    enabled: bool = True  # run the live mapping worker beside the recorder
    mesh: MeshConfig = MeshConfig()
    windows: WindowsConfig = WindowsConfig()
    model: ModelConfig = ModelConfig()
    inputs: InputsConfig = InputsConfig()
    fast_fit: FastFitConfig = FastFitConfig()
    faithful_fit: FaithfulFitConfig = FaithfulFitConfig()
    maskless: MasklessConfig = MasklessConfig()
    runtime: RuntimeConfig = RuntimeConfig()
    live_view: LiveViewConfig = LiveViewConfig()
    segmentation: SegmentationConfig = SegmentationConfig()


class StatusConfig(_Strict):
    bind_address: str = "127.0.0.1"
    port: int = Field(8088, ge=0, le=65535)


class CarConfig(_Strict):
    vehicle: VehicleConfig = VehicleConfig()
    sensors: SensorsConfig
    bus: BusConfig = BusConfig()
    recorder: RecorderConfig = RecorderConfig()
    mapper: MapperConfig = MapperConfig()
    status: StatusConfig = StatusConfig()

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


def data_dir(config: CarConfig, config_file: str | Path, override: str | Path | None = None) -> Path:
    """The folder for log segments and maps: the override, else recorder.output_dir (relative to the config)."""
    return Path(override) if override else resolve_path(config_file, config.recorder.output_dir)


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
