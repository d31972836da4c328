"""The mapper's section of the car's configuration (`mapper:`): the mesh, the windows, the model, the inputs, the
two fits, the maskless mode, the threads, the live view and where the semantic masks come from."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from daemon.spine.config_model import StrictModel


class LearningRates(StrictModel):
    """Adam learning rates of the faithful fit, one optimiser per parameter group."""

    elevation_mlp: float = Field(0.01, gt=0)  # the elevation MLP's weights
    colour_mlps: float = Field(0.005, gt=0)  # the per-camera colour decoders' weights
    semantics: float = Field(0.1, gt=0)  # the per-vertex semantic logits (row-sparse Adam)
    colour_codes: float = Field(0.005, gt=0)  # the per-vertex colour codes (row-sparse Adam)


class LossWeights(StrictModel):
    """Weights of the faithful fit's four losses in its total."""

    rgb: float = Field(1.0, ge=0)  # L1 colour of the rendered pixels against the images
    semantics: float = Field(1.0, ge=0)  # cross-entropy of the rendered semantics against the masks
    elevation: float = Field(1.0, ge=0)  # L1 of the vertex heights against the Lidar ground points under them
    smoothness: float = Field(1.0, ge=0)  # L1 of the height differences between neighbouring vertices


class LiveViewConfig(StrictModel):
    """The mapper's optional Foxglove WebSocket live view of the growing map (mapping.live.live_view)."""

    enabled: bool = False
    bind_address: str = "127.0.0.1"
    port: int = Field(8765, ge=0, le=65535)  # 0: any free port


MaskClassName = Literal["road", "lane_marking", "curb", "manhole", "background", "obstacle"]


class SegmentationConfig(StrictModel):
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


class MeshConfig(StrictModel):
    """The road mesh (mapping.method.road_mesh): equilateral triangles cut to a corridor around the trajectory."""

    side_m: float = Field(0.1, gt=0, le=2)  # triangle side (m): the map's resolution, and the BEV rasters' cell
    corridor_half_width_m: float = Field(15.0, gt=0)  # the mesh reaches this far (m) either side of the
    # trajectory; the Lidar ground points are kept within the same corridor


class WindowsConfig(StrictModel):
    """The stretch of road around a point of the trajectory that the model spans (the paper's 80 m + 80 m)."""

    before_m: float = Field(80.0, gt=0)  # metres of drive behind the point: the faithful fit's step window, the
    # evaluation's view window (up to 10 m behind a camera) and the live worker's window start
    after_m: float = Field(80.0, gt=0)  # metres ahead of it; before_m + after_m also scales the elevation
    # MLP's positional encoding, and the live worker's windows are centred every (before_m + after_m) / 2


class ModelConfig(StrictModel):
    """The EMIE-MAP model both fits train (mapping.method.road_map)."""

    colour_code_dim: int = Field(32, gt=0)  # length of each vertex's colour code
    positional_encoding_dim: int = Field(22, gt=1)  # sin/cos features of x, y fed to the elevation MLP
    elevation_mlp_layers: int = Field(8, ge=1)  # hidden layers of the elevation MLP
    elevation_mlp_width: int = Field(128, ge=1)  # units per hidden layer of the elevation MLP
    colour_mlp_layers: int = Field(2, ge=1)  # layers of each camera's colour decoder
    colour_mlp_width: int = Field(16, ge=1)  # units per hidden layer of each colour decoder
    seed: int = 0  # seeds torch and numpy for the initial weights and the fits' sampling (the live worker
    # derives one per window from it)


class InputsConfig(StrictModel):
    """Which camera frames and Lidar scans of a drive the fits are given (mapping.inputs, mapping.live)."""

    keyframe_spacing_m: float = Field(1.0, ge=0)  # per camera, a frame each time the vehicle has moved this
    # far (m) since the last one kept; 0: every frame
    lidar_every_n_scans: int = Field(2, ge=1)  # Lidar scans used: every n-th (a scan: one frame id's packets)


class CameraCheckConfig(StrictModel):
    """Each camera's orientation checked against the poses by its own images (mapping.localization
    .camera_orientation) in every reconstruction (`roadlog reconstruct`, the fleet's and the live worker's windows),
    on its training keyframes: the turn of its mount that makes the poses agree with their epipolar geometry."""

    mode: Literal["off", "report", "apply"] = "off"  # report: the check in metrics.json, a warning for a camera
    # that is off (see warn_deg); apply: also the keyframes of such a camera corrected by it before the fits (a bad
    # extrinsic calibration, or the poses' constant heading error, which the check cannot tell apart and which the
    # map takes the same way). Off by default: ~0.3 s a keyframe pair on 2 cores
    max_pairs: int = Field(80, ge=3)  # keyframe pairs of a camera matched at most (evenly along the drive)
    min_inliers: int = Field(20, ge=8)  # matches a pair's essential matrix needs to be used
    min_step_m: float = Field(0.5, gt=0)  # the camera's travel a pair needs (the direction of a shorter one is noise)
    warn_deg: float = Field(1.0, gt=0)  # a camera is off when its yaw or pitch correction is above this (degrees)
    # and above three standard errors, read from at least as many keyframe pairs as were refused: on mounts that are
    # right the check reads up to ~0.4 deg where the road has texture (bench/RESULTS.md, bench/camera_check.py)


class FastFitConfig(StrictModel):
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
    lidar_detail_prior: float = Field(0.03, ge=0)  # points' worth of the neighbours' mean detail at each vertex
    # (few points: the vertex follows its neighbours; mapping.fits.lidar_detail)
    photometric_elevation: bool = True  # with no Lidar ground (none, --no-lidar): the residual MLP fitted to the
    # heights of a plane sweep at the lattice nodes (mapping.fits.photometric_elevation); False: z = z0 there
    photometric_span_m: float = Field(0.4, gt=0)  # the sweep's candidate heights: z0 - span .. z0 + span (m) ...
    photometric_step_m: float = Field(0.02, gt=0)  # ... this far apart (m; the best one refined by a parabola)
    photometric_patch_m: float = Field(0.6, gt=0)  # side (m) of the square ground patch compared across views
    photometric_patch_samples: int = Field(7, ge=2)  # points along each side of the patch
    photometric_min_views: int = Field(3, ge=2)  # views a node's candidate height needs
    photometric_min_std: float = Field(2.0, ge=0)  # grey levels (0-255): a view's patch below this is blank
    photometric_distinct_m: float = Field(0.3, gt=0)  # a node's confidence: its peak NCC less the best one at
    # least this far (m) from its best height
    photometric_behind_m: float = Field(3.0, ge=0)  # a keyframe reads the nodes from this far (m) behind it ...
    photometric_ahead_m: float = Field(12.0, gt=0)  # ... to this far ahead
    photometric_refine_span_m: float = Field(0.0, ge=0)  # > 0: then a second sweep +-this (m) around the MLP's
    # first fit, each patch on that surface, and the MLP fitted again to its heights; 0 (default): one sweep on
    # z0. 0.1 helps the random worlds (camera-only MAE median 5.01 -> 4.03 cm) but hurt the real KITTI drives
    # (0005 saturation ratio 0.84 -> 0.54, 01 PSNR 22.07 -> 21.73 dB): off until that is understood
    behind_m: float = Field(3.0, ge=0)  # a keyframe observes the vertices from this far (m) behind its
    # trajectory point ...
    ahead_m: float = Field(12.0, gt=0)  # ... to this far (m) ahead: farther views blur
    edge_min_views: int = Field(1, ge=1)  # a vertex is mapped when at least this many views supervised it ...
    edge_opening_m: float = Field(1.0, ge=0)  # ... and a disc of this radius (m) inside the mapped area reaches it:
    # the teeth of the views' reach (one per keyframe) left out (mapping.fits.mapped_area); 0: every seen vertex
    label_sharp_m: float | None = Field(0.01, gt=0)  # a pixel's label counts fully where the pixel covers at
    # most this much ground (m) along the line of sight, in proportion beyond (far views count less;
    # mapping.fits.vertex_observations.label_weights); None: every label counts 1
    label_footprint_subdivision: int = Field(4, ge=1, le=8)  # a view's labels are read over each vertex's
    # footprint on the lattice that splits the mesh's edges into this many parts (mapping.fits.vertex_observations);
    # 2, the half-edge read: the observe stage ~25 % cheaper, 12-16 cm markings aliased (lane IoU ~0.2 lower)
    lane_line_gain: float = Field(2.0, ge=0)  # a lane marking's label frequency is raised by this much times its
    # excess over the neighbours on both sides on the centres of lines the views blurred
    # (mapping.fits.lane_line_centres); 0: the plain frequencies
    colour_encoder_steps: int = Field(200, ge=1)  # steps of the joint colour encoder / decoder fit
    colour_batch: int = Field(4096, ge=1)  # vertices sampled per colour step
    colour_decoder_lr: float = Field(0.005, gt=0)  # Adam learning rate of the per-camera colour decoders
    colour_encoder_lr: float = Field(0.01, gt=0)  # Adam learning rate of the colour encoder (the codes' source)


class PoseRefinementConfig(StrictModel):
    """Corrections of the trajectory's poses fitted to the map before the fast fit observes the keyframes
    (mapping.fits.pose_refinement): knots along the track, fitted coarse to fine to the photometric agreement of
    the training keyframes, with a prior towards zero and smoothness between knots; with Lidar, their height, roll
    and pitch from the Lidar ground first (mapping.fits.lidar_registration)."""

    enabled: bool = False  # off: the poses as given (`roadlog reconstruct --pose-refinement on|off` overrides)
    knot_spacing_m: float = Field(2.0, gt=0)  # the corrections' knots this far apart along the track, linear between
    blur_px: tuple[float, ...] = Field((4.0, 2.0, 1.0), min_length=1)  # one round per entry: the grey images
    # blurred by this Gaussian sigma (px; 0: sharp), coarse to fine
    steps: int = Field(60, ge=1)  # Adam steps per round
    samples_per_m: int = Field(300, ge=1)  # the most textured vertices per metre of track the views are compared at
    min_views: int = Field(3, ge=1)  # a vertex takes part when at least this many views see it
    lr: float = Field(0.05, gt=0)  # Adam learning rate of the knots (in 10 cm and 1 degree units; cosine decay)
    photometric_lr: float = Field(0.01, gt=0)  # Adam learning rate of each view's gain and offset
    photometric_sigma: float = Field(0.03, gt=0)  # grey error (0-1) of one unit of loss; the Huber loss is
    # quadratic below it, linear above
    prior_m: float = Field(0.2, gt=0)  # the prior's standard deviation of a knot's translation (m) ...
    prior_deg: float = Field(0.5, gt=0)  # ... and rotation (degrees)
    prior_weight: float = Field(0.05, ge=0)  # weight of the prior (mean over knots of the squared ratios)
    smooth_m: float = Field(0.1, gt=0)  # the smoothness's standard deviation of the change between knots (m) ...
    smooth_deg: float = Field(0.2, gt=0)  # ... and (degrees)
    smooth_weight: float = Field(0.05, ge=0)  # weight of the smoothness (mean over neighbouring knots)
    lidar_registration: bool = True  # with Lidar ground points: their height, roll and pitch registered first
    # (mapping.fits.lidar_registration), the ground re-placed with them, and held by the photometric fit
    lidar_cell_m: float = Field(0.25, gt=0)  # the registration compares the points within cells of this side (m)
    lidar_point_sigma_m: float = Field(0.02, gt=0)  # a ground point's height error (m), against the prior
    lidar_huber_m: float = Field(0.03, gt=0)  # points further than this from their cell's height count less
    lidar_rounds: int = Field(4, ge=1)  # reweighted least-squares rounds
    lidar_max_points: int = Field(3_000_000, ge=1)  # an even subsample of the ground points when there are more
    # (~0.9 GB and ~1 min a million in the registrations; a 128-beam Lidar gives ~7,000 a metre of track, so
    # drives up to ~400 m keep every point: the horizontal registration's 0.1 m stage needs them, bench/RESULTS.md)
    lidar_horizontal: bool = False  # with Lidar ground points: every axis from them, x, y and yaw too (mapping.fits
    # .lidar_horizontal_registration: the intensity contrast, paint, and the kerbs' slopes, fitted with the heights);
    # no photometric fit. Offline the drive is then read again with the corrected trajectory (`roadlog reconstruct
    # --pose-refinement lidar`)
    lidar_horizontal_blur_m: tuple[float, ...] = Field((0.4, 0.2, 0.1), min_length=1)  # its fields' Gaussian
    # sigma (m), one stage per entry, coarse to fine
    lidar_horizontal_rounds: int = Field(3, ge=1)  # Gauss-Newton steps per stage
    lidar_horizontal_min_cell_m: float = Field(0.1, gt=0)  # its cells (each stage's sigma / 2) at least this size
    lidar_contrast_sigma: float = Field(0.3, gt=0)  # a point's intensity contrast error (log units)
    lidar_horizontal_huber: float = Field(1.0, gt=0)  # residuals beyond this many sigmas count less

    @model_validator(mode="after")
    def _horizontal_needs_the_height_registration(self) -> PoseRefinementConfig:
        if self.lidar_horizontal and not self.lidar_registration:  # it starts from the heights' corrections
            raise ValueError("lidar_horizontal needs lidar_registration (it starts from the height registration's "
                             "corrections)")
        return self


class MasklessConfig(StrictModel):
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
    consensus: bool = True  # fast fit: a vertex's colour from such views is their consensus, not their mean: the
    # views within consensus_tolerance of the one of weighted median brightness (mapping.fits.colour_consensus)
    consensus_tolerance: float = Field(0.08, gt=0)  # mean absolute RGB ([0, 1]) within which a view agrees
    consensus_near_m: float = Field(5.0, gt=0)  # a view weighs 1 / (1 + (d / this)^2) at a vertex d metres away

    @model_validator(mode="after")
    def _heights_in_order(self) -> MasklessConfig:
        if self.standing_max_m <= self.standing_min_m:
            raise ValueError("standing_max_m must be above standing_min_m")
        return self


class FaithfulFitConfig(StrictModel):
    """The paper-faithful fit (`roadlog reconstruct --faithful`; mapping.fits.faithful_fit): every pixel of every
    batch image rendered against the whole window, each step."""

    learning_rates: LearningRates = LearningRates()
    loss_weights: LossWeights = LossWeights()
    epochs: int = Field(5, ge=1)  # passes over the training keyframes
    batch_size: int = Field(8, ge=1)  # adjacent keyframes (along the trajectory) per step


class RuntimeConfig(StrictModel):
    """Threads of the mapper's pools and of torch. They change the speed only: the sums that split over threads
    split the same way whatever their timing, but their count is part of the order of the float sums."""

    torch_threads_fast_fit: int = Field(1, ge=1)  # torch intra-op threads of the fast fit and its evaluation
    # (its MLPs are small: more threads spin against each other)
    torch_threads_faithful_fit: int = Field(2, ge=1)  # torch intra-op threads of the faithful fit
    observe_threads: int = Field(2, ge=1)  # threads projecting the keyframes onto the vertices (fast fit)
    lidar_ground_threads: int = Field(2, ge=1)  # threads extracting the Lidar ground, scan by scan
    lidar_detail_threads: int = Field(2, ge=1)  # threads (and parts of the point sums) of the Lidar detail
    photometric_threads: int = Field(2, ge=1)  # threads of the camera-only plane sweep (parts of its keyframes)
    evaluation_threads: int = Field(2, ge=1)  # threads rendering and scoring the evaluation's views
    raster_threads: int = Field(2, ge=1)  # threads filling the bird's-eye rasters (blocks of rows)


class LagConfig(StrictModel):
    """What the live worker does when it cannot keep up with the car, and at its stop (mapping.live.lag_policy)."""

    max_behind_m: float | None = Field(1000.0, gt=0)  # when the next window ended more than this far (m) behind the
    # car, the windows up to the newest ended one are skipped: journalled `skipped` with their time span and log
    # segments (`roadlog reconstruct` on those segments maps them later), counted in its health; None: never skip
    # (a replay never skips: its process-table entry says --no-skip). Keep it well above the road driven in the 2 s
    # a window's inputs reach past its end (60 m at 30 m/s): a worker that keeps up is that far behind
    stop_reserve_s: float = Field(60.0, ge=0)  # of its stop timeout (--stop-timeout-s), the seconds kept for the
    # final map: after SIGTERM no window starts that would not end before the timeout less this
    min_window_wall_s: float = Field(0.0, ge=0)  # each window takes at least this long (s): a mapper slower than
    # the car without the CPU it would cost (tests, soaks); 0: as fast as it fits


DEVICES = ("auto", "cpu", "cuda")  # mapper.device's values (mapping.method.compute_device)


class MapperConfig(StrictModel):
    """The road-surface mapper (the live worker and `roadlog reconstruct`)."""

    enabled: bool = True  # run the live mapping worker beside the recorder
    device: Literal["auto", "cpu", "cuda"] = "auto"  # torch device of the fits (mapping.method.compute_device):
    # auto = cuda when torch sees a CUDA GPU, else cpu; cuda without one is a configuration error at start
    mesh: MeshConfig = MeshConfig()
    windows: WindowsConfig = WindowsConfig()
    model: ModelConfig = ModelConfig()
    inputs: InputsConfig = InputsConfig()
    camera_check: CameraCheckConfig = CameraCheckConfig()
    fast_fit: FastFitConfig = FastFitConfig()
    faithful_fit: FaithfulFitConfig = FaithfulFitConfig()
    pose_refinement: PoseRefinementConfig = PoseRefinementConfig()
    maskless: MasklessConfig = MasklessConfig()
    runtime: RuntimeConfig = RuntimeConfig()
    live_view: LiveViewConfig = LiveViewConfig()
    lag: LagConfig = LagConfig()
    segmentation: SegmentationConfig = SegmentationConfig()
