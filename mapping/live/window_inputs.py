"""What one window of the live mapping worker (mapping.live.mapping_worker) is optimised from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapping.localization.trajectory import HorizontalTrack, Trajectory
from mapping.method.scene_data import Keyframe, StandingPoints


@dataclass
class WindowInputs:
    """What one window is optimised from, gathered from the spool and the small streams."""

    centre_m: float  # the window's centre, start and end along the drive (end clipped to the distance driven)
    start_m: float
    end_m: float
    t_lo_ns: int  # the host time span the window covers (within the fused trajectory)
    t_hi_ns: int
    trajectory: Trajectory  # fused over the small streams held, up to t_hi_ns + INPUT_HORIZON_NS
    path: HorizontalTrack  # the window's track: times in seconds from t_lo_ns
    keyframes: list[Keyframe]
    ground: np.ndarray | None  # Lidar ground points, None without a Lidar
    provenance: dict  # host time range, per-topic seq ranges, log segments, input counts (into the journal)
    standing: StandingPoints | None  # what the Lidar saw standing on the road, for keyframes without masks
