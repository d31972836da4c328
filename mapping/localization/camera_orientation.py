"""Each camera's orientation checked against the poses by its own images' epipolar geometry.

A camera frame is placed in the world by the vehicle's pose and the camera's extrinsics. Between two keyframes of
one camera, the poses say in which direction the camera moved (in the first frame's camera axes); SIFT matches of
the two images, through an essential matrix (OpenCV, MAGSAC++), say the same from the pixels alone. If the camera's
extrinsics (or the poses' heading) are off by a fixed rotation, every pair's image direction turned by it is the
poses' direction. `check_orientations` fits that rotation per camera (robust least squares over pairs one and two
keyframes apart) about the two axes across the direction of travel, and reports it as a turn of the mount in yaw and
pitch: a turn about the direction of travel (roll) does not move it and is not checked. The check cannot tell a
mount's error from a constant heading error of the poses: both place that camera's pixels the same way, and the
correction fixes both for the map. `corrected_keyframes` applies the significant corrections to the keyframes' poses.

The image's own rotation is not used: a small turn and a small sideways step look alike in a narrow view (the
bas-relief ambiguity), so a direction solved under the poses' rotation inherits that rotation's error many times
over (on KITTI 01, 0.02 deg of relative yaw became 0.7 deg of direction); the free essential matrix's direction is
noisier per pair but not biased by the poses.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from daemon.spine.mapper_config import CameraCheckConfig
from daemon.spine.semantic_classes import SemanticClass
from mapping.method.scene_data import CameraModel, Keyframe

SIFT_FEATURES = 2000  # per image, the strongest
SIFT_CONTRAST = 0.01  # OpenCV's default 0.04 finds ~100 features in a side camera's view of plain asphalt
RATIO_TEST = 0.75  # Lowe's ratio for a SIFT match
RANSAC_PX = 1.0  # the essential matrix's inlier distance (pixels)
ROBUST_SCALE_RAD = np.deg2rad(0.3)  # soft-L1 scale of a pair's residual: pairs further off count less
OBSTACLE_MARGIN_PX = 15  # features this near an obstacle's pixels are left out too (a feature spans ~10 px)
PAIR_GAPS = (1, 2)  # keyframe pairs this many keyframes apart (the longer step sees the direction better)
MIN_PAIRS = 8  # pairs a camera's check needs (fewer: no reading; their spread says too little of its error)


@dataclass(frozen=True)
class PairMotion:
    """One keyframe pair of one camera: the second camera's centre as a unit direction in the first camera's axes,
    from the images and from the poses."""

    image_direction: np.ndarray  # (3,)
    pose_direction: np.ndarray  # (3,)


@dataclass(frozen=True)
class CameraOrientation:
    """What a camera's images say about its orientation: the turn of its mount (degrees, yaw about the vehicle's z
    up, pitch about its y left) that makes the poses agree with them, with each one's standard error, the
    camera-axes rotation that corrects its keyframes, and the pairs it rests on."""

    camera: str
    pitch_deg: float
    yaw_deg: float
    std_deg: tuple[float, float]  # pitch, yaw
    pairs_used: int
    pairs_refused: int  # a step shorter than min_step_m, too few matches, or no essential matrix
    median_angle_before_deg: float  # the pairs' direction disagreement, median, before and after the correction
    median_angle_after_deg: float
    camera_rotation: np.ndarray  # (3, 3) C: a keyframe's T_world_camera[:3, :3] @ C is its corrected orientation

    def summary(self) -> dict:
        return {"pitch_deg": round(self.pitch_deg, 3), "yaw_deg": round(self.yaw_deg, 3),
                "std_deg": [round(s, 3) for s in self.std_deg],
                "pairs_used": self.pairs_used, "pairs_refused": self.pairs_refused,
                "median_angle_before_deg": round(self.median_angle_before_deg, 3),
                "median_angle_after_deg": round(self.median_angle_after_deg, 3)}


def _undistorted_pixels(points: np.ndarray, camera: CameraModel) -> np.ndarray:
    if not camera.distorted:
        return points
    return cv2.undistortPoints(points.reshape(-1, 1, 2), camera.K, np.float64(camera.distortion),
                               P=camera.K).reshape(-1, 2)


def ratio_matches(features_a, features_b, matcher) -> tuple[np.ndarray, np.ndarray]:
    """The two images' SIFT matches (features: keypoints, descriptors) that pass Lowe's ratio test: their pixels in
    each, (M, 2) each."""
    (k1, d1), (k2, d2) = features_a, features_b
    pairs = [m for m, n in (p for p in matcher.knnMatch(d1, d2, k=2) if len(p) == 2)
             if m.distance < RATIO_TEST * n.distance]
    return (np.float64([k1[m.queryIdx].pt for m in pairs]).reshape(-1, 2),
            np.float64([k2[m.trainIdx].pt for m in pairs]).reshape(-1, 2))


def image_direction(features_a, features_b, camera: CameraModel, matcher, min_inliers: int,
                    pose_direction: np.ndarray) -> np.ndarray | None:
    """The second camera's centre direction in the first's axes from the two images' SIFT features (keypoints,
    descriptors) through an essential matrix (MAGSAC++), or None when fewer than `min_inliers` matches fit one. Of
    its two signs, the one within 90 degrees of `pose_direction`."""
    (k1, d1), (k2, d2) = features_a, features_b
    if d1 is None or d2 is None or len(k1) < min_inliers or len(k2) < min_inliers:
        return None
    p1, p2 = ratio_matches(features_a, features_b, matcher)
    if len(p1) < min_inliers:
        return None
    p1, p2 = _undistorted_pixels(p1, camera), _undistorted_pixels(p2, camera)
    # SIFT gives one spot several keypoints (one per orientation): each match once
    _, first = np.unique(np.round(np.c_[p1, p2], 1), axis=0, return_index=True)
    p1, p2 = p1[np.sort(first)], p2[np.sort(first)]
    if len(p1) < min_inliers:
        return None
    try:  # OpenCV's plain RANSAC five-point solver asserts on some samples (solvePoly); MAGSAC++ did not here
        e, inl = cv2.findEssentialMat(p1, p2, camera.K, cv2.USAC_MAGSAC, 0.999, RANSAC_PX)
        if e is None or e.shape != (3, 3):
            return None
        count, r, t, _ = cv2.recoverPose(e, p1, p2, camera.K, mask=inl)
    except cv2.error:
        return None
    if count < min_inliers:
        return None
    centre = -r.T @ t.ravel()
    return centre if centre @ pose_direction >= 0 else -centre


def static_mask(keyframe: Keyframe) -> np.ndarray | None:
    """Where a keyframe's features may be found: away from what its semantics label an obstacle (cars and people
    move, and a car ahead matched frame to frame gives the essential matrix of its own motion); None (anywhere)
    without semantics."""
    if keyframe.semantics is None:
        return None
    moving = (keyframe.semantics == SemanticClass.OBSTACLE).astype(np.uint8)
    return np.where(cv2.dilate(moving, np.ones((OBSTACLE_MARGIN_PX, OBSTACLE_MARGIN_PX), np.uint8)) > 0, 0,
                    255).astype(np.uint8)


def pose_motion(a: Keyframe, b: Keyframe) -> tuple[np.ndarray, float]:
    """What the keyframes' poses say: the second camera's centre direction in the first's axes, and the step's
    length (m)."""
    step = a.T_world_camera[:3, :3].T @ (b.T_world_camera[:3, 3] - a.T_world_camera[:3, 3])
    length = float(np.linalg.norm(step))
    return step / max(length, 1e-12), length


def pair_motions(keyframes: list[Keyframe], camera: CameraModel, *, max_pairs: int, min_step_m: float,
                 min_inliers: int) -> tuple[list[PairMotion], int]:
    """Pairs of one camera's keyframes one and two apart (every k-th so that at most `max_pairs` are tried) measured
    both ways, and the count of pairs refused."""
    frames = sorted((k for k in keyframes if k.camera == camera.name), key=lambda k: k.timestamp)
    candidates = [(frames[i], frames[i + gap]) for i in range(len(frames)) for gap in PAIR_GAPS
                  if i + gap < len(frames)]
    stride = max(1, -(-len(candidates) // max_pairs))
    candidates = candidates[::stride]
    sift = cv2.SIFT_create(nfeatures=SIFT_FEATURES, contrastThreshold=SIFT_CONTRAST)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    features: dict[int, tuple] = {}

    def feats(k: Keyframe):
        if id(k) not in features:
            features[id(k)] = sift.detectAndCompute(cv2.cvtColor(k.image, cv2.COLOR_RGB2GRAY), static_mask(k))
        return features[id(k)]

    motions, refused = [], 0
    for a, b in candidates:
        direction, length = pose_motion(a, b)
        seen = (image_direction(feats(a), feats(b), camera, matcher, min_inliers, direction)
                if length >= min_step_m else None)
        if seen is None:
            refused += 1
            continue
        motions.append(PairMotion(seen, direction))
    return motions, refused


def _angles_deg(directions_a: np.ndarray, directions_b: np.ndarray) -> np.ndarray:
    """The angles (degrees) between the rows of two (N, 3) arrays of unit vectors."""
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", directions_a, directions_b), -1, 1)))


def fit_orientation(camera: str, motions: list[PairMotion], refused: int,
                    camera_to_vehicle: np.ndarray | None) -> CameraOrientation | None:
    """The camera-axes rotation C, about the two axes across the mean direction of travel, that turns the images'
    directions into the poses' (soft-L1 least squares; None with fewer than MIN_PAIRS pairs), reported about the
    vehicle's axes through the camera's extrinsic rotation `camera_to_vehicle` (3x3; None: unknown, the "pitch"
    and "yaw" are then the turn about the camera's own y (down) and z (forward) axes)."""
    if len(motions) < MIN_PAIRS:
        return None
    to_vehicle = np.eye(3) if camera_to_vehicle is None else camera_to_vehicle
    seen = np.array([m.image_direction for m in motions])
    placed = np.array([m.pose_direction for m in motions])
    travel = placed.mean(axis=0)
    travel /= np.linalg.norm(travel)
    across = np.linalg.svd(travel[None, :])[2][1:]  # (2, 3): two unit axes across the direction of travel

    def turn(ab: np.ndarray) -> np.ndarray:
        return Rotation.from_rotvec(ab @ across).as_matrix()

    def residuals(ab: np.ndarray) -> np.ndarray:  # ~ each pair's angle, about its axis
        return np.cross(seen @ turn(ab).T, placed).ravel()

    fit = least_squares(residuals, np.zeros(2), loss="soft_l1", f_scale=ROBUST_SCALE_RAD)
    c = turn(fit.x)
    # the correction as a turn of the mount in the vehicle's axes: R_vc' = Q R_vc with Q = R_vc C R_vc^T
    _, pitch, yaw = np.degrees(Rotation.from_matrix(to_vehicle @ c @ to_vehicle.T).as_rotvec())
    # each one's standard error: the pairs' robust spread left about that axis (MAD) over the root of the pairs
    # that count apart (each keyframe is in up to two pairs of each gap: half of them)
    left = np.cross(seen @ c.T, placed) @ to_vehicle.T  # (N, 3) each pair's remaining turn in the vehicle's axes
    spread = 1.4826 * np.median(np.abs(left - np.median(left, axis=0)), axis=0)
    std = tuple(float(np.degrees(spread[i]) / np.sqrt(len(motions) / len(PAIR_GAPS))) for i in (1, 2))
    before, after = _angles_deg(seen, placed), _angles_deg(seen @ c.T, placed)
    return CameraOrientation(camera, float(pitch), float(yaw), std, len(motions), refused,
                             float(np.median(before)), float(np.median(after)), c)


def check_orientations(keyframes: list[Keyframe], cameras: dict[str, CameraModel],
                       setting: CameraCheckConfig) -> dict[str, CameraOrientation | None]:
    """Every camera's orientation check (None for a camera with fewer than MIN_PAIRS usable pairs)."""
    out = {}
    for name, camera in cameras.items():
        motions, refused = pair_motions(keyframes, camera, max_pairs=setting.max_pairs,
                                        min_step_m=setting.min_step_m, min_inliers=setting.min_inliers)
        out[name] = fit_orientation(name, motions, refused, camera.mount_rotation)
    return out


def significant(check: CameraOrientation | None, setting: CameraCheckConfig) -> bool:
    """Whether a camera's check says its orientation is off: its yaw or pitch above `warn_deg` and above three
    standard errors, read from at least as many pairs as were refused (what a warning names and what `apply`
    corrects; a smaller reading is the check's own noise)."""
    if check is None or check.pairs_used < check.pairs_refused:  # most views gave no essential matrix: too little
        return False  # texture or too much traffic to trust its reading (the random worlds' plain asphalt)
    angles = (check.pitch_deg, check.yaw_deg)
    return any(abs(angle) > max(setting.warn_deg, 3 * std) for angle, std in zip(angles, check.std_deg, strict=True))


def camera_check_figures(checks: dict[str, CameraOrientation | None], setting: CameraCheckConfig) -> dict:
    """metrics.json's camera_check: the mode, and per camera the check's summary (None: too few pairs) and whether
    it is significant (`warned`; under `apply` those cameras' keyframes were corrected)."""
    return {"mode": setting.mode, "warn_deg": setting.warn_deg,
            "cameras": {name: None if check is None else {**check.summary(), "warned": significant(check, setting)}
                        for name, check in checks.items()}}


def corrected_keyframes(keyframes: list[Keyframe], checks: dict[str, CameraOrientation | None],
                        setting: CameraCheckConfig) -> list[Keyframe]:
    """The keyframes with the orientation of each camera whose check is significant corrected (T_world_camera's
    rotation times C); the other cameras' as they were."""
    turns = {name: check.camera_rotation for name, check in checks.items() if significant(check, setting)}
    out = []
    for k in keyframes:
        if k.camera not in turns:
            out.append(k)
            continue
        pose = k.T_world_camera.copy()
        pose[:3, :3] = pose[:3, :3] @ turns[k.camera]
        out.append(replace(k, T_world_camera=pose))
    return out
