"""A live mapping worker fed a recorded log directly (no bus thread), for tests of its windows."""

from pathlib import Path

from daemon.log_format.reader import read_log
from mapping.live.worker_loop import MappingWorker
from tests.daemon_fixtures import private_config

SMALL_WINDOWS = {"windows": {"before_m": 10.0, "after_m": 10.0}, "mesh": {"side_m": 0.25, "corridor_half_width_m": 6.0},
                 "inputs": {"keyframe_spacing_m": 2.0}}


def worker_fed(folder: Path, drive: Path, shift_ns: int = 0, topic_by_topic: bool = False,
               mapper: dict | None = None, leave_out: tuple[str, ...] = ()) -> MappingWorker:
    """A worker (small windows, and any `mapper` settings) fed the log but the topics in `leave_out`: arrivals moved
    by shift_ns, in log order or per topic."""
    folder.mkdir()
    config, config_path = private_config(folder, mapper=SMALL_WINDOWS | (mapper or {}))
    worker = MappingWorker(config, str(config_path), str(folder / "data"))
    records = [r for r in read_log([drive]) if r.topic in worker.reader.topics and r.topic not in leave_out]
    if topic_by_topic:
        records.sort(key=lambda r: r.topic)  # stable: each topic still in its own order
    for r in records:
        r.message.host_mono_ns = r.log_time_ns + shift_ns
        worker.reader.take(r.topic, r.message)
    worker.update_distance()
    return worker
