"""The torch device the fits run on (`mapper.device`, `--device`): `auto` (cuda when torch sees a CUDA GPU, else
cpu), `cpu` or `cuda`; and the mark on the fits' optimisation loops, inside which no tensor crosses between the
host and the device (data moves once before a loop, results once after; tests watch the mark).
"""

from __future__ import annotations

import contextvars
import platform
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from daemon.spine.config import ConfigError
from daemon.spine.mapper_config import DEVICES

_IN_LOOP: contextvars.ContextVar[str | None] = contextvars.ContextVar("optimisation_loop", default=None)


def resolve_device(name: str, key: str = "mapper.device") -> torch.device:
    """The device `name` (one of DEVICES) stands for here; ConfigError (naming `key`) for cuda without a GPU."""
    if name not in DEVICES:
        raise ConfigError(f"{key}: expected one of {', '.join(DEVICES)}, got {name!r}")
    if name == "cpu":
        return torch.device("cpu")
    available = torch.cuda.is_available()
    if name == "cuda" and not available:
        build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        raise ConfigError(f"{key}: cuda asked for, but torch sees no CUDA GPU here (torch {torch.__version__}, "
                          f"{build}); use cpu, or auto (cuda when a GPU is present, else cpu)")
    return torch.device("cuda" if available else "cpu")


def with_device(car, device: str | None):
    """The car config `car` with `mapper.device` set to `device` (a --device option; None: as configured)."""
    if device is None:
        return car
    return car.model_copy(update={"mapper": car.mapper.model_copy(update={"device": device})})


def device_name(device: torch.device) -> str:
    """The device in words, for benches and metrics: the GPU's name, or the CPU's."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"cpu ({platform.processor() or platform.machine()})"


@contextmanager
def optimisation_loop(name: str) -> Iterator[None]:
    """Marks the optimisation loop `name` (the steps of a fit): inside it no tensor is copied to or from the
    host (no .item(), .cpu(), .numpy(), .tolist(), torch.from_numpy, host-array indexing). Costs nothing."""
    token = _IN_LOOP.set(name)
    try:
        yield
    finally:
        _IN_LOOP.reset(token)


def current_loop() -> str | None:
    """The name of the optimisation loop running in this thread, None outside every loop."""
    return _IN_LOOP.get()
