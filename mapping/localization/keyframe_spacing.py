"""Keyframe spacing: of one camera's frames in time order, one each time the vehicle has moved a given distance
since the last one kept (`mapper.inputs.keyframe_spacing_m`). The one rule the offline inputs, the live
worker and the reconstruction all apply; each passes the distance it measures (3-D along the fused
trajectory, or horizontal along the reconstruction's track)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

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
