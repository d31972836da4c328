"""GNSS fixes perturbed before the pose fusion, for bench/pose_noise.py `--noise-at fixes` (issue 17 item 5).

A receiver's position error wanders: per axis a first-order Gauss-Markov process (time constant `tau_s`, seconds to
tens of seconds: multipath, atmosphere and a float ambiguity change slowly) plus white noise (each epoch's own), the
vertical `vertical_ratio` times the horizontal. The draw over the drive's fixes is scaled so that its 3-D RMS is
exactly `position_rms_m` (as bench/pose_noise.py's injected pose error is), and each fix reports that sigma as its
covariance (diagonal east, north, up: what a receiver's hAcc / vAcc or GST say; the fusion weighs the fixes by it,
times FusionSettings.gnss_position_sigma_scale). The receiver's Doppler velocities (`gnss/velocity`) are left as
logged: they do not share the position error and are accurate to a few cm/s (the simulator's 2 cm/s white).

`perturb_log` writes a copy of a log with only its `gnss/fix` messages moved; `fused_error` fuses a log's trajectory
as the mapper does and gives its error against the simulator's true trajectory, split into the drive's common shift
and turn (which nothing on board can see against the receiver) and the rest. `registered_miou` scores a map's
bird's-eye semantics against the truth as placed and after the map's best 2-D shift (an evaluation lens, as a SLAM
benchmark aligns a trajectory before its ATE; the shift is bench/fleet.py's, polished on the score; no turn).
"""

from __future__ import annotations

import importlib.util
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon.log_format.foxglove_schemas import to_well_known  # noqa: E402
from daemon.log_format.reader import decode_record, read_log  # noqa: E402
from daemon.spine.local_frame import LocalFrame  # noqa: E402
from daemon.spine.messages import GnssFix, TimeAnchor  # noqa: E402
from daemon.spine.semantic_classes import NUM_MAP_CLASSES  # noqa: E402
from daemon.spine.topics import FUSION_TOPICS, GNSS_FIX, GNSS_VELOCITY, IMU, TIME_ANCHOR, WHEEL_SPEEDS  # noqa: E402
from mapping.fleet.drive_merge import DriveLayer  # noqa: E402
from mapping.inputs.drive_inputs import fuse_log_trajectory  # noqa: E402
from mapping.localization.pose_noise import _rigid_part  # noqa: E402
from mapping.localization.sensor_time import fit_clocks  # noqa: E402
from mapping.offline.reconstruct_command import config_from_logs  # noqa: E402
from mapping.outputs.map_metrics import confusion, miou_pct  # noqa: E402


@dataclass(frozen=True)
class FixNoise:
    position_rms_m: float = 0.2  # 3-D RMS of the error over the drive's fixes
    tau_s: float = 10.0  # the Gauss-Markov part's time constant
    white_fraction: float = 0.2  # of each axis's variance, independent per epoch
    vertical_ratio: float = 1.5  # vertical sigma over each horizontal axis's
    seed: int = 0

    def sigmas_m(self) -> tuple[float, float]:
        """Each horizontal axis's sigma and the vertical's, for the 3-D RMS asked for."""
        h = self.position_rms_m / np.sqrt(2.0 + self.vertical_ratio ** 2)
        return float(h), float(self.vertical_ratio * h)


def gauss_markov(times_s: np.ndarray, sigma: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """A stationary first-order Gauss-Markov process (standard deviation `sigma`, correlation exp(-dt / tau_s)) at
    the given increasing times."""
    t = np.asarray(times_s, np.float64)
    out = np.empty(len(t))
    if len(t) == 0:
        return out
    steps = rng.standard_normal(len(t))
    out[0] = sigma * steps[0]
    a = np.exp(-np.diff(t) / tau_s)
    for i in range(1, len(t)):
        out[i] = a[i - 1] * out[i - 1] + sigma * np.sqrt(1.0 - a[i - 1] ** 2) * steps[i]
    return out


def fix_errors(times_s: np.ndarray, noise: FixNoise) -> np.ndarray:
    """The ENU error (N, 3) m of fixes at `times_s`, scaled to the 3-D RMS asked for."""
    rng = np.random.default_rng(noise.seed)
    h, v = noise.sigmas_m()
    w = noise.white_fraction
    error = np.stack([gauss_markov(times_s, s * np.sqrt(1.0 - w), noise.tau_s, rng)
                      + rng.normal(0.0, s * np.sqrt(w), len(times_s)) for s in (h, h, v)], 1)
    rms = float(np.sqrt((error ** 2).sum(1).mean())) if len(error) else 0.0
    return error * (noise.position_rms_m / rms) if rms > 0 else error


def perturb_log(src: Path, dst: Path, noise: FixNoise) -> dict:
    """Copy the log `src` to `dst` with every `gnss/fix` moved by fix_errors (at the fixes' sensor times) and its
    covariance set to the noise's sigmas; every other record as it was. Returns the error drawn (cm)."""
    with open(src, "rb") as f:
        reader = make_reader(f)
        fixes = [decode_record(s, c, m) for s, c, m in reader.iter_messages(topics=[GNSS_FIX])]
    times = np.array([m.sensor_time_ns for m in fixes], np.float64)
    error = fix_errors((times - times[0]) / 1e9, noise)
    frame = LocalFrame(fixes[0].latitude_deg, fixes[0].longitude_deg, fixes[0].altitude_m)
    enu = frame.geodetic_to_enu(np.array([m.latitude_deg for m in fixes]), np.array([m.longitude_deg for m in fixes]),
                                np.array([m.altitude_m for m in fixes]))
    lat, lon, alt = frame.enu_to_geodetic(enu + error)
    h, v = noise.sigmas_m()
    cov = (h * h, 0.0, 0.0, 0.0, h * h, 0.0, 0.0, 0.0, v * v)
    moved = {m.sensor_time_ns: GnssFix(m.seq, m.sensor_time_ns, m.host_mono_ns, float(lat[i]), float(lon[i]),
                                       float(alt[i]), cov, 2) for i, m in enumerate(fixes)}
    with open(src, "rb") as f, open(dst, "wb") as g:
        reader = make_reader(f)
        header = reader.get_header()
        writer = Writer(g, compression=CompressionType.LZ4)
        writer.start(profile=header.profile, library=header.library)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0), channel.metadata)
            data = message.data
            if channel.topic == GNSS_FIX:
                fix = decode_record(schema, channel, message)
                data = to_well_known(moved[fix.sensor_time_ns]).SerializeToString()
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time, message.sequence)
        writer.finish()
    return {"fixes": len(fixes), "error_rms_cm": 100.0 * float(np.sqrt((error ** 2).sum(1).mean())),
            "horizontal_rms_cm": 100.0 * float(np.sqrt((error[:, :2] ** 2).sum(1).mean())),
            "vertical_rms_cm": 100.0 * float(np.sqrt((error[:, 2] ** 2).mean())),
            "mean_enu_cm": (100.0 * error.mean(0)).round(2).tolist(), "reported_sigma_h_v_cm": [100 * h, 100 * v]}


def fused_trajectory(log: Path, origin: LocalFrame):
    """The log's trajectory fused as the mapper fuses it (mapping.inputs.drive_inputs, the car config recorded in
    the log), in `origin`'s frame."""
    config, _ = config_from_logs([str(log)])
    by_topic: dict[str, list] = {t: [] for t in FUSION_TOPICS}
    anchors = []
    for rec in read_log([log], topics={*FUSION_TOPICS, TIME_ANCHOR}):
        if isinstance(rec.message, TimeAnchor):
            anchors.append((rec.message.host_mono_ns, rec.message.utc_ns))
        else:
            by_topic[rec.topic].append(rec.message)
    clocks = fit_clocks(by_topic, anchors)
    return fuse_log_trajectory(by_topic[GNSS_FIX], by_topic[IMU], by_topic[WHEEL_SPEEDS], config, origin, clocks,
                               by_topic[GNSS_VELOCITY])


def fused_error(log: Path, gt_path: Path) -> dict:
    """The fused trajectory's error against the simulator's true one (the vehicle's reference point, over the
    drive at the truth's 200 Hz): 3-D and horizontal RMS (cm); the horizontal error's mean in the track's frame
    (`common_along_cm`, `common_across_cm`) and the drive's rigid turn (`rigid_turn_deg`), what a registration of
    the drive against itself cannot see, and the RMS left without that shift and turn (`nonrigid_horizontal_rms_cm`,
    mapping.localization.pose_noise's split); the heading's RMS error (deg)."""
    gt = np.load(gt_path)
    origin = LocalFrame(*(float(v) for v in gt["enu_origin_lat_lon_alt"]))
    trajectory = fused_trajectory(log, origin)
    t = gt["trajectory_host_mono_ns"]
    inside = (t >= trajectory.times_ns[0]) & (t <= trajectory.times_ns[-1])
    position, quat = trajectory.interpolate(t[inside])
    true = gt["trajectory_position_enu"][inside]
    error = position - true
    true_rot = Rotation.from_quat(gt["trajectory_quaternion_xyzw"][inside])
    forward = true_rot.apply([1.0, 0.0, 0.0])
    heading = np.arctan2(forward[:, 1], forward[:, 0])
    c, s = np.cos(heading), np.sin(heading)
    along, across = c * error[:, 0] + s * error[:, 1], -s * error[:, 0] + c * error[:, 1]
    yaw = (Rotation.from_quat(quat) * true_rot.inv()).as_rotvec()[:, 2]
    return {"position_rms_cm": 100.0 * float(np.sqrt((error ** 2).sum(1).mean())),
            "horizontal_rms_cm": 100.0 * float(np.sqrt((error[:, :2] ** 2).sum(1).mean())),
            "vertical_rms_cm": 100.0 * float(np.sqrt((error[:, 2] ** 2).mean())),
            "common_along_cm": 100.0 * float(along.mean()), "common_across_cm": 100.0 * float(across.mean()),
            "common_horizontal_cm": 100.0 * float(np.hypot(*error[:, :2].mean(0))),
            **_rigid_part(error[:, :2], true[:, :2]),
            "yaw_rms_deg": float(np.rad2deg(np.sqrt((yaw ** 2).mean())))}


_fleet_spec = importlib.util.spec_from_file_location("fleet_bench", Path(__file__).with_name("fleet.py"))
fleet_bench = importlib.util.module_from_spec(_fleet_spec)
_fleet_spec.loader.exec_module(fleet_bench)
MAX_SHIFT_M = 0.5  # the shifts searched
POLISH_M, POLISH_STEP_M = 0.03, 0.01  # the registered shift polished on the score this far around fleet's


def registered_miou(out: Path, gt_path: Path) -> dict:
    """The map's bird's-eye mIoU from its `bev_semantics.npy` (at every other 5 cm true cell, as
    mapping.outputs.map_metrics.truth_cells, the map's classes interpolated there, where both have a class) as
    placed, and registered: with the map moved by the horizontal shift that overlays it best on the truth, first
    bench/fleet.py's (drive_merge.estimate_shift on the markings', curbs' and manholes' layers, sub-cell), then
    polished on the score within POLISH_M (the raster's 10 cm cells hold its thin classes at a phase). No turn is
    searched: the fused tracks' rigid turns are below 0.01 deg here (fused_error). The truth is taken onto the
    map's grid for the shift by interpolation, not by the nearest cell (the map's cell centres can lie on the
    truth's cell edges). An evaluation lens, as a SLAM benchmark aligns a trajectory before its ATE: what the map
    scores had the positioning put it where it belongs; the target is the map as placed."""
    bev = json.loads((out / "bev.json").read_text())
    labels = np.load(out / "bev_semantics.npy")
    height = np.load(out / "bev_elevation.npy")
    gt = np.load(gt_path)
    res, (x0, y0) = float(bev["resolution_m"]), bev["origin_xy"]
    rows, cols = labels.shape
    t_res, (tx, ty) = float(gt["grid_resolution_m"]), gt["grid_origin_xy"]
    t_cls, t_z = gt["semantic"], gt["elevation"]
    t_rows, t_cols = t_cls.shape

    # the truth on the map's grid, for the shift: its classes (one-hot) and heights interpolated bilinearly at the
    # map's cell centres (which may fall on the truth's cell edges: a nearest cell would be a coin toss there)
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    fi, fj = (y0 + ii * res - ty) / t_res - 0.5, (x0 + jj * res - tx) / t_res - 0.5
    i0, j0 = np.floor(fi).astype(np.int64), np.floor(fj).astype(np.int64)
    wi, wj = fi - i0, fj - j0
    prob = np.zeros((rows, cols, NUM_MAP_CLASSES), np.float32)
    z_sum, z_weight = np.zeros((rows, cols)), np.zeros((rows, cols))
    for di_, dj_, w in ((0, 0, (1 - wi) * (1 - wj)), (0, 1, (1 - wi) * wj), (1, 0, wi * (1 - wj)), (1, 1, wi * wj)):
        ti, tj = i0 + di_, j0 + dj_
        inside = (ti >= 0) & (ti < t_rows) & (tj >= 0) & (tj < t_cols)
        ti, tj = np.where(inside, ti, 0), np.where(inside, tj, 0)
        cls, z = t_cls[ti, tj], t_z[ti, tj]
        known = inside & (cls < NUM_MAP_CLASSES)
        r, c = np.nonzero(known)
        prob[r, c, cls[known]] += w[known]
        ok = inside & np.isfinite(z)
        z_sum[ok] += w[ok] * z[ok]
        z_weight[ok] += w[ok]
    total = prob.sum(-1)
    labelled_truth = total > 0.5
    prob = np.where(labelled_truth[..., None], prob / np.maximum(total, 1e-6)[..., None], 0.0).astype(np.float32)
    height_truth = np.where(z_weight > 0.5, z_sum / np.maximum(z_weight, 1e-6), np.nan).astype(np.float32)
    truth = DriveLayer("truth", height_truth, (labelled_truth & np.isfinite(height_truth)).astype(np.float32), prob, {})
    found = fleet_bench.estimate_shift(truth, fleet_bench.one_hot_layer("map", height, labels),
                                       int(np.ceil(MAX_SHIFT_M / res)), res)
    di, dj = found.shift or (0.0, 0.0)  # the map's cell x matches the truth's at x + (di, dj) cells
    shift = np.array([dj * res, di * res])

    qi, qj = np.mgrid[0:t_rows:2, 0:t_cols:2]  # every other true cell: 10 cm, as the map metrics
    qi, qj = qi.ravel(), qj.ravel()
    known = t_cls[qi, qj] < NUM_MAP_CLASSES
    qi, qj = qi[known], qj[known]
    q = np.stack([tx + (qj + 0.5) * t_res, ty + (qi + 0.5) * t_res], 1)

    def score(move: np.ndarray) -> float | None:
        # the map's labels at each true cell's place once the map is moved by `move`: its one-hot classes
        # interpolated bilinearly between the four nearest cells (all labelled), so that the score follows a shift
        # below a cell
        p = q - move
        fi, fj = (p[:, 1] - y0) / res, (p[:, 0] - x0) / res
        i0, j0 = np.floor(fi).astype(np.int64), np.floor(fj).astype(np.int64)
        wi, wj = fi - i0, fj - j0
        ok = (i0 >= 0) & (i0 + 1 < rows) & (j0 >= 0) & (j0 + 1 < cols)
        i0, j0, wi, wj, rest = i0[ok], j0[ok], wi[ok], wj[ok], np.nonzero(ok)[0]
        prob = np.zeros((len(i0), NUM_MAP_CLASSES))
        labelled = np.ones(len(i0), bool)
        for di_, dj_, w in ((0, 0, (1 - wi) * (1 - wj)), (0, 1, (1 - wi) * wj), (1, 0, wi * (1 - wj)), (1, 1, wi * wj)):
            lab = labels[i0 + di_, j0 + dj_]
            labelled &= lab < NUM_MAP_CLASSES
            np.add.at(prob, (np.arange(len(lab)), np.minimum(lab, NUM_MAP_CLASSES - 1)), w)
        pred, rest = prob[labelled].argmax(1), rest[labelled]
        return miou_pct(confusion(pred.astype(np.int64), t_cls[qi[rest], qj[rest]].astype(np.int64),
                                  np.ones(len(rest), bool)))

    # the raster's 10 cm cells hold its thin classes (a 14 cm line) at a phase: its score moves by steps with a
    # shift (measured: 0.1 point at 2 cm, 8 points at 4 cm), so the shift is polished on the score itself within
    # POLISH_M of fleet's (every POLISH_STEP_M), the same for every map, the exact poses' included
    found_shift, best = shift, score(shift)
    steps = np.arange(-POLISH_M, POLISH_M + 1e-9, POLISH_STEP_M)
    for dx in steps:
        for dy in steps:
            value = score(found_shift + np.array([dx, dy]))
            if value is not None and (best is None or value > best):
                best, shift = value, found_shift + np.array([dx, dy])
    return {"miou_pct_raster": score(np.zeros(2)), "miou_pct_registered": best,
            "fleet_shift_to_truth_cm": (100.0 * found_shift).tolist(),
            "shift_to_truth_cm": (100.0 * shift).tolist(), "shift_overlap_cells": found.overlap_cells}
