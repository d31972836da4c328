"""A simulated drive played as an endless one (soaks): one pass lasts the drive's seconds, and pass k plays every
record k passes later, its sensor times (and a Lidar's frame ids) carried on as the sensors would go on counting."""

from __future__ import annotations

from pathlib import Path

from daemon.log_format.reader import read_metadata
from daemon.spine.config import ConfigError


def loop_period_ns(drive_mcap: Path) -> int:
    """How long one pass of a drive made by `roadlog simulate` lasts (its `seconds`): every sensor's events lie in
    [0, seconds), so pass k + 1 continues each sensor's rhythm where pass k ends."""
    seconds = read_metadata(drive_mcap).get("roadlog", {}).get("seconds")
    if seconds is None:
        raise ConfigError(f"{drive_mcap}: not a drive made by `roadlog simulate` (no `seconds` in its metadata): it "
                          f"cannot be looped")
    return int(float(seconds) * 1e9)
