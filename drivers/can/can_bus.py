"""Opening the configured python-can bus (the driver process, the simulator and the tests open it the same way)."""

from __future__ import annotations

import can

from daemon.spine.config import CanConfig


def open_can_bus(config: CanConfig, **bus_kwargs: object) -> can.BusABC:
    """A python-can bus for the configured interface and channel (extra keywords go to can.Bus)."""
    kwargs: dict[str, object] = {"interface": config.interface, "channel": config.channel, **config.options,
                                 **bus_kwargs}
    if config.bitrate is not None:
        kwargs["bitrate"] = config.bitrate
    return can.Bus(**kwargs)
