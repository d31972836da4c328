"""Lidar horizontal registration (mapping.fits.lidar_horizontal_registration): ground points placed with a pose whose
along-track, across-track and heading error wander (on a grade, with a height error too) are registered back by the
lane paint's intensity and the kerbs; exact poses get no correction; the intensity contrast of a Lidar whose signal
falls with range shows paint the same near and far."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from daemon.spine.mapper_config import PoseRefinementConfig
from mapping.fits.lidar_horizontal_registration import register_horizontal
from mapping.fits.lidar_registration import register_ground
from mapping.inputs.lidar_ground import intensity_contrast
from mapping.localization.trajectory import HorizontalTrack

SETTINGS = PoseRefinementConfig(enabled=True, lidar_horizontal=True)
SPEED = 8.0  # m/s along x
GRADE = 0.04  # on a grade an along-track shift and a height change look alike to the heights alone


def _paint(xy: np.ndarray) -> np.ndarray:
    """Dashed lane lines (3 m of 12) at |y| = 1.6 m, solid edge lines at |y| = 4.8 m, a 0.6 m manhole every 20 m."""
    dashed = (np.abs(np.abs(xy[:, 1]) - 1.6) < 0.11) & ((xy[:, 0] % 12.0) < 3.0)
    edge = np.abs(np.abs(xy[:, 1]) - 4.8) < 0.11
    manhole = np.hypot((xy[:, 0] % 20.0) - 10.0, xy[:, 1] + 3.2) < 0.3
    return dashed | edge | manhole


def _albedo(xy: np.ndarray) -> np.ndarray:
    """Paint 0.8; asphalt 0.1 with a smooth texture of +-30 % (patches, wear) that changes along the road too."""
    x, y = xy[:, 0], xy[:, 1]
    texture = 1 + 0.15 * (np.sin(x * 2.1 + 0.7 * np.sin(y * 1.3)) + np.sin(x * 0.9 - y * 1.7))
    return np.where(_paint(xy), 0.8, 0.1 * texture)


def _surface(xy: np.ndarray) -> np.ndarray:
    return GRADE * xy[:, 0] + 0.15 * (np.abs(xy[:, 1]) > 5.5)


def _drive(seconds: float, error_cm: float, rng: np.random.Generator):
    """The track as placed (true track plus a smooth error in x, y, z and yaw drawn every 0.5 s) and the ground
    points as that pose placed them (1 cm range noise, 20 % intensity noise, a signal falling with range), their
    times and intensity contrasts; and the error (x, y, z, yaw) at the track's times."""
    t = np.arange(0.0, seconds, 0.01)
    true = np.stack([SPEED * t, np.zeros_like(t), GRADE * SPEED * t + 1.6], 1)
    knots = np.arange(0.0, seconds + 0.5, 0.5)
    draw = rng.standard_normal((len(knots), 4))
    error = np.stack([np.interp(t, knots, draw[:, k]) for k in range(4)], 1)
    error[:, :3] *= error_cm / 100.0 / np.sqrt(3)
    error[:, 3] *= np.deg2rad(0.1) * (error_cm > 0)
    placed = true + error[:, :3]
    points, times, contrast = [], [], []
    for scan_t in np.arange(0.0, seconds - 0.1, 0.1):
        n = 15_000
        distance, azimuth = rng.uniform(2.0, 30.0, n), rng.uniform(-np.pi, np.pi, n)
        firing = scan_t + (azimuth + np.pi) / (2 * np.pi) * 0.1
        i = np.clip(np.searchsorted(t, firing), 0, len(t) - 1)
        xy = true[i, :2] + np.stack([distance * np.cos(azimuth), distance * np.sin(azimuth)], 1)
        keep = np.abs(xy[:, 1]) < 8.0
        xy, i, distance, firing = xy[keep], i[keep], distance[keep], firing[keep]
        ground = np.concatenate([xy, (_surface(xy) + rng.normal(0, 0.01, len(xy)))[:, None]], 1)
        signal = _albedo(xy) * (1 + 0.2 * rng.standard_normal(len(xy))) * 4000 / distance ** 2
        yaw = np.stack([np.zeros(len(i)), np.zeros(len(i)), error[i, 3]], 1)
        points.append(placed[i] + Rotation.from_rotvec(yaw).apply(ground - true[i]))
        times.append(firing)
        contrast.append(intensity_contrast(signal, distance))
    return HorizontalTrack(t, placed), np.concatenate(points), np.concatenate(times), np.concatenate(contrast), error


def _registered(track, points, times, contrast):
    height, _ = register_ground(points, times, track, SETTINGS, {})
    return register_horizontal(points, times, contrast, track, SETTINGS, {}, height)


def _left(error: np.ndarray, correction: np.ndarray) -> tuple[float, float]:
    """RMS of the error before and after the correction, each less its mean (a shift or turn of the whole map is
    not observable from the Lidar alone)."""
    before = error - error.mean()
    after = error + correction
    return float(np.sqrt((before ** 2).mean())), float(np.sqrt(((after - after.mean()) ** 2).mean()))


@pytest.mark.parametrize("seed", [0, 1])
def test_a_wandering_along_across_and_heading_error_is_registered_by_paint_and_kerbs(seed):
    track, points, times, contrast, error = _drive(5.0, 20.0, np.random.default_rng(seed))
    timings = {}
    height, _ = register_ground(points, times, track, SETTINGS, timings)
    corrections, figures = register_horizontal(points, times, contrast, track, SETTINGS, timings, height)
    inside = (track.times > 0.5) & (track.times < 4.5)  # the ends are seen from one side only
    position, rotation = corrections.at(track.horizontal_distance_at(track.times[inside]))
    for axis, correction in ((0, position[:, 0]), (1, position[:, 1]), (2, position[:, 2])):
        before, after = _left(error[inside, axis], correction)
        assert after < 0.5 * before, (axis, before, after)  # along-track too, on the grade
    before, after = _left(error[inside, 3], rotation[:, 2])
    assert after < before  # the heading's error (0.05 degrees, 1.3 cm at 15 m) is near what the points resolve
    assert figures["points_with_contrast"] == figures["points"] > 100_000
    assert figures["rounds"][-1]["contrast_rms"] < figures["rounds"][0]["contrast_rms"]
    assert timings["lidar_horizontal_registration_wall_s"] > 0


def test_the_heights_alone_leave_the_along_track_error_on_a_grade():
    """What the horizontal registration adds: the height registration alone (x, y, yaw zero) cannot move a point
    along the road, and the horizontal one without intensities (heights and kerbs only) gets across-track but not
    along-track back."""
    track, points, times, contrast, error = _drive(5.0, 20.0, np.random.default_rng(0))
    height, _ = register_ground(points, times, track, SETTINGS, {})
    assert np.abs(height.position_m[:, :2]).max() == 0
    corrections, figures = register_horizontal(points, times, None, track, SETTINGS, {}, height)
    assert figures["points_with_contrast"] == 0
    inside = (track.times > 0.5) & (track.times < 4.5)
    position, _ = corrections.at(track.horizontal_distance_at(track.times[inside]))
    along_before, along_after = _left(error[inside, 0], position[:, 0])
    across_before, across_after = _left(error[inside, 1], position[:, 1])
    assert across_after < 0.5 * across_before  # the kerbs
    assert along_after > 0.6 * along_before  # nothing along the road without the paint


def test_exact_poses_get_no_correction():
    track, points, times, contrast, _ = _drive(4.0, 0.0, np.random.default_rng(3))
    corrections, figures = _registered(track, points, times, contrast)
    inside = (track.times > 0.5) & (track.times < 3.5)  # the ends are seen from one side only
    position, rotation = corrections.at(track.horizontal_distance_at(track.times[inside]))
    assert np.sqrt((position ** 2).sum(1).mean()) < 0.04  # the along-track's noise floor here: ~3 cm
    assert np.rad2deg(np.sqrt((rotation ** 2).sum(1).mean())) < 0.03
    assert figures["position_rms_cm"] < 5.0


def test_intensity_contrast_shows_paint_alike_near_and_far():
    rng = np.random.default_rng(5)
    distance = rng.uniform(2.0, 40.0, 20_000)
    paint = rng.random(len(distance)) < 0.1
    signal = np.where(paint, 0.8, 0.1) * 4000 / distance ** 2 + 3  # a signal falling with range, and its floor
    contrast = intensity_contrast(signal, distance)
    near, far = distance < 10, distance > 30
    assert abs(np.median(contrast[~paint])) < 0.05  # the road itself around zero at every range
    assert np.median(contrast[paint & near]) > 1.0 and np.median(contrast[paint & far]) > 0.4
    raw = np.log1p(signal)  # without the normalisation the road near and far would differ more than paint does
    assert np.median(raw[~paint & near]) - np.median(raw[~paint & far]) > 1.0
    assert np.isnan(intensity_contrast(None, distance)).all()
