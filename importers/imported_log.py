"""Where an importer writes: a log that appears whole or not at all (OUT.partial renamed over OUT when the import
finishes, removed when it fails; its host times are the dataset's UTC stamps, so they are its log times), the summary
every importer prints, and a pose matrix as a pose message."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from daemon.log_format.writer import LogWriter
from daemon.spine.config import CarConfig
from daemon.spine.messages import VehiclePose


@dataclass(frozen=True)
class ImportSummary:
    log: Path
    messages: dict[str, int]  # per topic
    drive_s: float  # first to last camera frame
    wall_s: float  # the import's own time

    def as_json(self) -> str:
        return json.dumps({"log": str(self.log), "messages": self.messages, "drive_s": round(self.drive_s, 3),
                           "wall_s": round(self.wall_s, 3)})


@contextlib.contextmanager
def imported_log(out: Path, config: CarConfig, metadata: dict[str, str]) -> Iterator[LogWriter]:
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    writer = LogWriter(partial, config, metadata=metadata, log_time_offset_ns=0)  # a dataset's host times are UTC
    try:
        yield writer
    except BaseException:
        writer.close()
        partial.unlink(missing_ok=True)
        raise
    writer.close()
    partial.replace(out)


def vehicle_pose(t_world_vehicle: np.ndarray, sensor_ns: int, host_ns: int, frame_id: str, seq: int = 0
                 ) -> VehiclePose:
    """A 4x4 vehicle -> world transform as the `pose` topic's message."""
    return VehiclePose(seq=seq, sensor_time_ns=sensor_ns, host_mono_ns=host_ns, frame_id=frame_id,
                       position_m=tuple(float(v) for v in t_world_vehicle[:3, 3]),
                       orientation_xyzw=tuple(float(v) for v in
                                              Rotation.from_matrix(t_world_vehicle[:3, :3]).as_quat()))
