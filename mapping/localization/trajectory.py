"""The vehicle's trajectory, one concept with two views:

- `Trajectory`: 6-DoF poses in a local ENU frame on the host clock (int64 ns): poses at any time (linear +
  SLERP) and by distance travelled, measured in 3-D along the path (`distance_3d_at`, ...). Pose fusion makes
  it; the inputs interpolate camera poses and Lidar scans on it and space keyframes by its distance.
- `HorizontalTrack`: the reference point's positions over seconds from a start, with distances measured
  horizontally (x, y) (`horizontal_distance_at`): what the road mesh, the fits and the evaluation take
  (`Trajectory.horizontal_track()`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from daemon.spine.local_frame import LocalFrame


@dataclass(frozen=True)
class Trajectory:
    """Poses of the vehicle reference frame (x forward, y left, z up) in the ENU frame of an origin.

    `quaternions[i]` (x, y, z, w) rotates vehicle-frame vectors into ENU; `positions[i]` is the reference
    point in ENU metres at `times_ns[i]` (strictly increasing, int64 nanoseconds).
    """

    times_ns: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float
    cumulative_distance_3d: np.ndarray = field(init=False, repr=False, compare=False)  # (N,) m at each pose
    _slerp: Slerp = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        times = np.asarray(self.times_ns, dtype=np.int64)
        positions = np.asarray(self.positions, dtype=np.float64)
        quaternions = np.asarray(self.quaternions, dtype=np.float64)
        n = len(times)
        if times.ndim != 1 or n < 2:
            raise ValueError(f"a trajectory needs at least 2 poses, got times of shape {times.shape}")
        if positions.shape != (n, 3) or quaternions.shape != (n, 4):
            raise ValueError(f"positions {positions.shape} / quaternions {quaternions.shape} for {n} times")
        if np.any(np.diff(times) <= 0):
            raise ValueError("times_ns must be strictly increasing")
        rotations = Rotation.from_quat(quaternions)  # normalises
        object.__setattr__(self, "times_ns", times)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "quaternions", rotations.as_quat())
        steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        object.__setattr__(self, "cumulative_distance_3d", np.concatenate([[0.0], np.cumsum(steps)]))
        object.__setattr__(self, "_slerp", Slerp(self._seconds(times), rotations))

    @property
    def local_frame(self) -> LocalFrame:
        return LocalFrame(self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)

    @property
    def rotations(self) -> Rotation:
        return Rotation.from_quat(self.quaternions)

    def _seconds(self, times_ns) -> np.ndarray:
        return (np.asarray(times_ns, dtype=np.int64) - self.times_ns[0]).astype(np.float64) * 1e-9

    def _check_covered(self, times_ns: np.ndarray) -> None:
        outside = (times_ns < self.times_ns[0]) | (times_ns > self.times_ns[-1])
        if np.any(outside):
            raise ValueError(f"{int(outside.sum())} of {len(times_ns)} times lie outside the trajectory "
                             f"[{self.times_ns[0]}, {self.times_ns[-1]}] ns")

    def interpolate(self, times_ns) -> tuple[np.ndarray, np.ndarray]:
        """Poses at arbitrary times inside the trajectory: (positions (M,3), quaternions (M,4) x,y,z,w)."""
        times = np.atleast_1d(np.asarray(times_ns, dtype=np.int64))
        self._check_covered(times)
        seconds, knots = self._seconds(times), self._seconds(self.times_ns)
        positions = np.stack([np.interp(seconds, knots, self.positions[:, k]) for k in range(3)], axis=1)
        return positions, self._slerp(seconds).as_quat()

    def distance_3d_at(self, times_ns) -> np.ndarray:
        """Distance travelled along the path (3-D) from the first pose, at each time (metres)."""
        times = np.atleast_1d(np.asarray(times_ns, dtype=np.int64))
        self._check_covered(times)
        return np.interp(self._seconds(times), self._seconds(self.times_ns), self.cumulative_distance_3d)

    def time_at_distance_3d(self, distances) -> np.ndarray:
        """First time (int64 ns) at which each distance along the path (3-D) is reached."""
        distances = np.atleast_1d(np.asarray(distances, dtype=np.float64))
        if np.any((distances < 0.0) | (distances > self.cumulative_distance_3d[-1])):
            raise ValueError(f"distances must lie in [0, {self.cumulative_distance_3d[-1]:.3f}] m")
        cumulative = self.cumulative_distance_3d
        after = np.clip(np.searchsorted(cumulative, distances, side="left"), 1, len(cumulative) - 1)
        before = after - 1  # the last pose short of the distance: the departure point after a stop
        span = cumulative[after] - cumulative[before]
        fraction = (distances - cumulative[before]) / np.where(span > 0.0, span, np.inf)
        steps_ns = self.times_ns[after] - self.times_ns[before]
        return self.times_ns[before] + np.round(fraction * steps_ns).astype(np.int64)

    def pose_at_distance_3d(self, distances) -> tuple[np.ndarray, np.ndarray]:
        """Poses where each distance along the path (3-D) is first reached: (positions (M,3), quaternions (M,4))."""
        return self.interpolate(self.time_at_distance_3d(distances))

    def horizontal_track(self) -> HorizontalTrack:
        """The trajectory as the reconstruction takes it: seconds from the first pose, positions."""
        t0 = self.times_ns[0]
        return HorizontalTrack((self.times_ns - t0) / 1e9, self.positions)


@dataclass(frozen=True)
class HorizontalTrack:
    """The vehicle reference point over time (world frame), distances measured horizontally (x, y)."""

    times: np.ndarray  # (N,) seconds, increasing
    positions: np.ndarray  # (N, 3) metres

    def horizontal_distance(self) -> np.ndarray:
        """Distance travelled (m) at each sample, horizontal."""
        step = np.linalg.norm(np.diff(self.positions[:, :2], axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(step)])

    def horizontal_distance_at(self, t: np.ndarray | float) -> np.ndarray:
        """Distance travelled (m, horizontal) at times `t` (seconds, the clock of `times`)."""
        return np.interp(t, self.times, self.horizontal_distance())

    @property
    def duration_s(self) -> float:
        return float(self.times[-1] - self.times[0])
