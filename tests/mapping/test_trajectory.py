"""Trajectory interpolation and distance lookups, and the geodetic / ECEF / local ENU conversions."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from daemon.spine.local_frame import (
    WGS84_A,
    WGS84_F,
    LocalFrame,
    ecef_to_enu_rotation,
    ecef_to_geodetic,
    geodetic_to_ecef,
)
from mapping.localization.trajectory import Trajectory

T0 = 1_700_000_000_123_456_789


def circle_trajectory(radius=50.0, speed=10.0, rate_hz=10.0, duration_s=20.0) -> Trajectory:
    """Driving anticlockwise on a circle at constant speed, climbing at 5 %, heading along the circle."""
    t = np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    angle = speed * t / radius
    positions = np.column_stack([radius * np.sin(angle), radius * (1 - np.cos(angle)), 0.05 * speed * t])
    rotations = Rotation.from_euler("ZY", np.column_stack([angle, np.full_like(t, -np.arctan(0.05))]))
    return Trajectory(T0 + np.round(t * 1e9).astype(np.int64), positions, rotations.as_quat(), 48.1, 11.5, 520.0)


def test_interpolation_returns_the_poses_at_the_knots():
    trajectory = circle_trajectory()
    positions, quaternions = trajectory.interpolate(trajectory.times_ns)
    np.testing.assert_allclose(positions, trajectory.positions, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(quaternions * trajectory.quaternions, axis=1)), 1.0, atol=1e-12)


def test_interpolation_is_linear_in_position_and_slerp_in_rotation():
    trajectory = circle_trajectory()
    middle = (trajectory.times_ns[:-1] + trajectory.times_ns[1:]) // 2
    positions, quaternions = trajectory.interpolate(middle)
    np.testing.assert_allclose(positions, 0.5 * (trajectory.positions[:-1] + trajectory.positions[1:]), atol=1e-6)
    # constant yaw rate about a fixed axis: SLERP is exact, the heading at mid-time is the mean heading
    yaw = Rotation.from_quat(quaternions).as_euler("ZYX")[:, 0]
    expected = 10.0 * (middle - T0) * 1e-9 / 50.0
    np.testing.assert_allclose(np.unwrap(yaw), expected, atol=1e-9)
    pitch = Rotation.from_quat(quaternions).as_euler("ZYX")[:, 1]
    np.testing.assert_allclose(pitch, -np.arctan(0.05), atol=1e-9)


def test_interpolation_outside_the_trajectory_is_refused():
    trajectory = circle_trajectory()
    with pytest.raises(ValueError, match="1 of 2 times lie outside"):
        trajectory.interpolate([trajectory.times_ns[0], trajectory.times_ns[-1] + 1])
    with pytest.raises(ValueError, match="outside"):
        trajectory.distance_3d_at(trajectory.times_ns[0] - 1)


def test_construction_checks_shapes_and_time_order():
    trajectory = circle_trajectory()
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(trajectory.times_ns[::-1], trajectory.positions, trajectory.quaternions, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="quaternions"):
        Trajectory(trajectory.times_ns, trajectory.positions, trajectory.quaternions[:-1], 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="at least 2 poses"):
        Trajectory(trajectory.times_ns[:1], trajectory.positions[:1], trajectory.quaternions[:1], 0.0, 0.0, 0.0)


def test_quaternions_are_normalised():
    trajectory = circle_trajectory()
    scaled = Trajectory(trajectory.times_ns, trajectory.positions, 3.0 * trajectory.quaternions, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(np.linalg.norm(scaled.quaternions, axis=1), 1.0)


def test_cumulative_distance_follows_the_path():
    trajectory = circle_trajectory(rate_hz=100.0)
    path_length = 10.0 * 20.0 * np.hypot(1.0, 0.05)
    assert trajectory.cumulative_distance_3d[-1] == pytest.approx(path_length, rel=1e-5)
    halfway = T0 + 10_000_000_000
    assert trajectory.distance_3d_at(halfway)[0] == pytest.approx(path_length / 2, rel=1e-5)


def test_time_at_distance_inverts_distance_at():
    trajectory = circle_trajectory()
    span = trajectory.times_ns[-1] - trajectory.times_ns[0]
    times = trajectory.times_ns[0] + np.linspace(0, span, 37).astype(np.int64)
    back = trajectory.time_at_distance_3d(trajectory.distance_3d_at(times))
    np.testing.assert_allclose(back, times, atol=2)  # nanoseconds
    with pytest.raises(ValueError, match="distances must lie"):
        trajectory.time_at_distance_3d([-1.0])


def test_a_stop_maps_its_distance_to_the_arrival_time():
    times = T0 + np.arange(6) * 1_000_000_000
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0], [3, 0, 0], [4, 0, 0]], dtype=float)
    trajectory = Trajectory(times, positions, np.tile([0.0, 0.0, 0.0, 1.0], (6, 1)), 0.0, 0.0, 0.0)
    found = trajectory.time_at_distance_3d([0.0, 0.5, 1.0, 1.5, 4.0])
    np.testing.assert_array_equal(found - T0, np.array([0.0, 0.5, 1.0, 3.25, 5.0]) * 1e9)
    positions_at, _ = trajectory.pose_at_distance_3d([1.5, 2.5])
    np.testing.assert_allclose(positions_at[:, 0], [1.5, 2.5])


def test_pose_at_distance_on_a_circle():
    trajectory = circle_trajectory(rate_hz=100.0)
    length = trajectory.cumulative_distance_3d[-1]
    positions, quaternions = trajectory.pose_at_distance_3d([length / 4])
    angle = (length / 4) / np.hypot(1.0, 0.05) / 50.0
    np.testing.assert_allclose(positions[0, :2], [50 * np.sin(angle), 50 * (1 - np.cos(angle))], atol=1e-4)
    assert Rotation.from_quat(quaternions[0]).as_euler("ZYX")[0] == pytest.approx(angle, abs=1e-5)


def test_geodetic_to_ecef_known_points():
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 0.0, 0.0), [WGS84_A, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 90.0, 100.0), [0.0, WGS84_A + 100.0, 0.0], atol=1e-8)
    polar_radius = WGS84_A * (1.0 - WGS84_F)
    np.testing.assert_allclose(geodetic_to_ecef(90.0, 0.0, 0.0), [0.0, 0.0, polar_radius], atol=1e-8)
    np.testing.assert_allclose(geodetic_to_ecef(-90.0, 0.0, 10.0), [0.0, 0.0, -polar_radius - 10.0], atol=1e-8)


@settings(max_examples=200, deadline=None)
@given(st.floats(-89.9, 89.9), st.floats(-180.0, 179.999), st.floats(-500.0, 20_000.0))
def test_ecef_round_trip_is_nanometre_exact(lat, lon, alt):
    lat2, lon2, alt2 = ecef_to_geodetic(geodetic_to_ecef(lat, lon, alt))
    assert abs(lat2 - lat) * 111_000 < 1e-8
    assert abs(((lon2 - lon + 180.0) % 360.0) - 180.0) * 111_000 * np.cos(np.radians(lat)) < 1e-8
    assert abs(alt2 - alt) < 1e-8


def test_enu_axes_point_east_north_up():
    frame = LocalFrame(48.137, 11.575, 520.0)
    np.testing.assert_allclose(frame.geodetic_to_enu(48.137, 11.575, 521.5), [0.0, 0.0, 1.5], atol=1e-8)
    north = frame.geodetic_to_enu(48.137 + 1e-5, 11.575, 520.0)
    east = frame.geodetic_to_enu(48.137, 11.575 + 1e-5, 520.0)
    # meridian and prime-vertical radii of curvature at the origin, plus its height
    s2 = np.sin(np.radians(48.137)) ** 2
    e2 = WGS84_F * (2 - WGS84_F)
    meridian = WGS84_A * (1 - e2) / (1 - e2 * s2) ** 1.5 + 520.0
    prime_vertical = WGS84_A / np.sqrt(1 - e2 * s2) + 520.0
    assert north[1] == pytest.approx(meridian * np.radians(1e-5), rel=1e-6) and abs(north[0]) < 1e-9
    assert east[0] == pytest.approx(prime_vertical * np.cos(np.radians(48.137)) * np.radians(1e-5), rel=1e-6)
    assert abs(east[1]) < 1e-6
    rotation = ecef_to_enu_rotation(48.137, 11.575)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(rotation) == pytest.approx(1.0)


def test_enu_round_trip_over_a_city():
    frame = LocalFrame(37.721, -122.4723, 31.6)
    enu = np.random.default_rng(0).uniform([-5000, -5000, -50], [5000, 5000, 200], (1000, 3))
    np.testing.assert_allclose(frame.geodetic_to_enu(*frame.enu_to_geodetic(enu)), enu, atol=1e-7)
    # the tangent plane leaves the ellipsoid: 5 km away a point at height 0 lies ~2 m below the plane
    assert frame.geodetic_to_enu(*frame.enu_to_geodetic([5000.0, 0.0, 0.0]))[2] == pytest.approx(0.0, abs=1e-7)
    assert frame.enu_to_geodetic([5000.0, 0.0, 0.0])[2] == pytest.approx(31.6 + 5000.0 ** 2 / (2 * 6.38e6), abs=0.05)


def test_trajectory_records_its_origin():
    trajectory = circle_trajectory()
    frame = trajectory.local_frame
    assert (frame.lat_deg, frame.lon_deg, frame.alt_m) == (48.1, 11.5, 520.0)


def test_the_horizontal_track_measures_distance_horizontally_the_trajectory_in_3d():
    """A straight 10 % ramp: 100 m ahead, 10 m up."""
    times = np.array([0, 10_000_000_000], np.int64)
    positions = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 10.0]])
    trajectory = Trajectory(times, positions, np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)), 0.0, 0.0, 0.0)
    track = trajectory.horizontal_track()
    assert trajectory.distance_3d_at(times[-1:])[0] == pytest.approx(np.hypot(100.0, 10.0))
    assert track.horizontal_distance_at(10.0) == pytest.approx(100.0)
    assert track.duration_s == 10.0 and np.array_equal(track.positions, positions)
