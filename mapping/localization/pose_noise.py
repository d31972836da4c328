"""Injected pose error, for measuring what pose error costs the map (`roadlog reconstruct --pose-noise-m`, the
benches): a trajectory perturbed by smooth random noise, and what is left of that error after a correction.

The error is drawn at knots `knot_every_s` apart in time (independent Gaussian per axis), linear in between, then
scaled so that over the trajectory's poses the 3-D position error has exactly the RMS asked for and each rotation
axis (a rotation vector in ENU, applied on the left about the vehicle's reference point) the per-axis RMS asked
for. Lidar scans and camera frames are then placed with the perturbed poses, as with a real pose error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mapping.localization.trajectory import Trajectory


@dataclass(frozen=True)
class PoseNoise:
    position_rms_m: float  # RMS of the 3-D position error over the trajectory's poses
    rotation_rms_deg: float = 0.0  # RMS of each axis of the rotation error (roll, pitch, yaw in ENU)
    knot_every_s: float = 0.5  # the error's independent draws this far apart in time, linear in between
    seed: int = 0

    def error_at(self, trajectory: Trajectory, seconds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The error (position (M, 3) m, rotation vector (M, 3) rad) at `seconds` from the trajectory's start."""
        knots, position, rotation = self._knots(trajectory)
        return _interpolated(knots, position, seconds), _interpolated(knots, rotation, seconds)

    def _knots(self, trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        seconds = (trajectory.times_ns - trajectory.times_ns[0]) / 1e9
        knots = np.arange(0.0, seconds[-1] + self.knot_every_s, self.knot_every_s)
        rng = np.random.default_rng(self.seed)
        position, rotation = rng.standard_normal((len(knots), 3)), rng.standard_normal((len(knots), 3))
        at_poses = _interpolated(knots, position, seconds)
        position *= self.position_rms_m / max(float(np.sqrt((at_poses ** 2).sum(1).mean())), 1e-12)
        at_poses = _interpolated(knots, rotation, seconds)
        rotation *= np.deg2rad(self.rotation_rms_deg) / np.maximum(np.sqrt((at_poses ** 2).mean(0)), 1e-12)
        return knots, position, rotation

    def figures(self) -> dict:
        return {"position_rms_cm": 100.0 * self.position_rms_m, "rotation_rms_deg": self.rotation_rms_deg,
                "knot_every_s": self.knot_every_s, "seed": self.seed}


def _interpolated(knots: np.ndarray, values: np.ndarray, seconds: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(seconds, knots, values[:, k]) for k in range(values.shape[1])], 1)


def perturbed(trajectory: Trajectory, noise: PoseNoise) -> Trajectory:
    """The trajectory with the noise's error added to every pose."""
    seconds = (trajectory.times_ns - trajectory.times_ns[0]) / 1e9
    position, rotation = noise.error_at(trajectory, seconds)
    rotations = Rotation.from_rotvec(rotation) * trajectory.rotations
    return Trajectory(trajectory.times_ns, trajectory.positions + position, rotations.as_quat(),
                      trajectory.origin_lat_deg, trajectory.origin_lon_deg, trajectory.origin_alt_m)


def residual_error(noise: PoseNoise, trajectory: Trajectory, seconds: np.ndarray,
                   correction_position: np.ndarray | None = None,
                   correction_rotation: np.ndarray | None = None) -> dict:
    """RMS of the vehicle pose's error left at `seconds` (the keyframes' times) once a correction (position (M, 3)
    m, rotation vector (M, 3) rad, applied as the noise is: on the left, about the reference point) is applied
    to the perturbed `trajectory`'s (None: none): position in cm (3-D and horizontal), rotation in degrees, and
    per component in the track's frame (along / across / vertical cm; roll / pitch / yaw degrees); the horizontal
    error's mean over `seconds` (`common_horizontal_cm`; signed, in the track's frame, `common_along_cm` and
    `common_across_cm`; and the yaw's, `common_yaw_deg`: a shift and turn of the whole drive, which no registration
    of the drive against itself can see) and its RMS less that mean (`relative_horizontal_rms_cm`); the same with
    the whole drive's turn too (`_rigid_part`)."""
    position, rotation = noise.error_at(trajectory, seconds)
    if correction_position is not None:
        position = position + correction_position
        rotation = (Rotation.from_rotvec(correction_rotation) * Rotation.from_rotvec(rotation)).as_rotvec()
    # per component in the track's frame at each time: along / across the heading, up; roll (about the heading),
    # pitch (about its left), yaw (about up)
    seconds = np.asarray(seconds, np.float64)
    places, quats = trajectory.interpolate(trajectory.times_ns[0] + np.rint(seconds * 1e9).astype(np.int64))
    forward = Rotation.from_quat(quats).apply([1.0, 0.0, 0.0])
    heading = np.arctan2(forward[:, 1], forward[:, 0])
    c, s = np.cos(heading), np.sin(heading)

    def in_track(v: np.ndarray) -> np.ndarray:
        return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)

    def rms(v: np.ndarray) -> list[float]:
        return [float(x) for x in np.sqrt((v ** 2).mean(0))]

    along, across, up = rms(100.0 * in_track(position))
    roll, pitch, yaw = rms(np.rad2deg(in_track(rotation)))
    # what a registration of the drive against itself cannot see, the error common to all its poses (its mean), and
    # what is left without it
    common = position.mean(0)
    relative = position[:, :2] - common[:2]
    common_along, common_across, _ = (100.0 * in_track(position).mean(0)).tolist()
    return {"common_horizontal_cm": 100.0 * float(np.hypot(*common[:2])),
            "common_along_cm": common_along, "common_across_cm": common_across,
            "relative_horizontal_rms_cm": 100.0 * float(np.sqrt((relative ** 2).sum(1).mean())),
            "common_yaw_deg": float(np.rad2deg(rotation[:, 2].mean())),
            **_rigid_part(position[:, :2], places[:, :2]),
            "position_rms_cm": 100.0 * float(np.sqrt((position ** 2).sum(1).mean())),
            "horizontal_rms_cm": 100.0 * float(np.sqrt((position[:, :2] ** 2).sum(1).mean())),
            "rotation_rms_deg": float(np.rad2deg(np.sqrt((rotation ** 2).sum(1).mean()))),
            "along_rms_cm": along, "across_rms_cm": across, "vertical_rms_cm": up,
            "roll_rms_deg": roll, "pitch_rms_deg": pitch, "yaw_rms_deg": yaw}


def _rigid_part(error: np.ndarray, places: np.ndarray) -> dict:
    """The horizontal errors (M, 2) at `places` (M, 2) as a shift and turn of the whole drive (least squares; a turn
    of a about the places' centroid moves a place q from it by a (-qy, qx)): `rigid_turn_deg` (a), and the RMS the
    errors have left without shift and turn, `nonrigid_horizontal_rms_cm`. A registration of the drive against
    itself cannot see a shift or a turn of all of it: from the Lidar and the cameras, this is the error it can
    remove."""
    q = places - places.mean(0)
    left = error - error.mean(0)
    turn_of = np.stack([-q[:, 1], q[:, 0]], 1)
    a = float((turn_of * left).sum() / max((q ** 2).sum(), 1e-12))
    rest = left - a * turn_of
    return {"rigid_turn_deg": float(np.rad2deg(a)),
            "nonrigid_horizontal_rms_cm": 100.0 * float(np.sqrt((rest ** 2).sum(1).mean()))}
