"""Keyframe spacing: of one camera's frames in time order, one each time the vehicle has moved a given distance
since the last one kept (`mapper.inputs.keyframe_spacing_m`). The one rule the offline inputs, the live
worker and the reconstruction all apply; each passes the distance it measures (3-D along the fused
trajectory, or horizontal along the reconstruction's track)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TypeVar

import numpy as np

Frame = TypeVar("Frame")


def spaced_by_distance(frames: Iterable[Frame], distance_m: Callable[[Frame], float], spacing_m: float,
                       usable: Callable[[Frame], bool] = lambda _: True) -> Iterator[Frame]:
    """The frames (one camera's, in time order) at least `spacing_m` past the last one kept, by `distance_m`
    (metres along the drive); the first is kept. `usable` is asked only of the frames far enough: one it
    refuses is passed over and the next one tried."""
    last = -float("inf")
    for frame in frames:
        s = distance_m(frame)
        if s - last < spacing_m or not usable(frame):
            continue
        last = s
        yield frame


def spaced_preferring(frames: Sequence[Frame], distance_m: Callable[[Frame], float], spacing_m: float,
                      preferred: Callable[[Frame], bool]) -> list[Frame]:
    """spaced_by_distance, where a frame that is not `preferred` (one without a mask) is passed over when a
    preferred one follows within `spacing_m` of it, and kept when none does: where the masks are missing (a
    segmenter slower than the camera, one that stopped, a car without one) the camera still gets its
    keyframes, without semantics. All frames preferred: exactly spaced_by_distance."""
    s = np.array([distance_m(f) for f in frames], np.float64)
    good = np.array([preferred(f) for f in frames], bool)
    good_s = np.sort(s[good])

    def usable(i: int) -> bool:
        if good[i]:
            return True
        k = np.searchsorted(good_s, s[i])  # the first preferred frame at or past this one
        return k == len(good_s) or good_s[k] > s[i] + spacing_m

    return [frames[i] for i in spaced_by_distance(range(len(frames)), lambda i: float(s[i]), spacing_m, usable)]
