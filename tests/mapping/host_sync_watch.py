"""A watch over the fits' optimisation loops (mapping.method.compute_device.optimisation_loop) that catches, on the
CPU, what would copy a tensor between the host and a GPU each step there.

On the CPU every tensor is on the host, so the watch looks at what the code asks for rather than where the data
is. A torch function mode (torch.overrides.TorchFunctionMode, which sees every torch call and tensor method) and a
profile hook (sys.setprofile, which sees torch.from_numpy: a builtin the mode does not) record, inside a marked
loop, every:
- read back: .item(), .tolist(), .numpy(), .cpu(), .cuda(), np.asarray(), float()/int()/bool()/index() of a
  tensor;
- move: .to(...) / .copy_ naming a device (nothing should move inside a loop: data moves once before it);
- host data entering: torch.from_numpy, torch.tensor / as_tensor / asarray, indexing a tensor with a numpy array
  or a list (torch copies such an index to the device each time);
- tensor made without `device=`: torch.zeros/ones/full/empty/arange/rand*/... (it would be a CPU tensor beside
  the GPU ones).
Calls made by torch's own Python code (torch.optim keeping its step count on the host, nn modules) are not ours to
judge and are left out: only calls whose caller is outside the torch package are recorded. What the watch cannot
see: the syncs a GPU makes by itself to size a result (nonzero, boolean masks, unique), which copy no tensor.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.overrides import TorchFunctionMode

from mapping.method.compute_device import current_loop

_TORCH_DIR = os.path.dirname(torch.__file__) + os.sep
_HERE = os.path.abspath(__file__)
_DISPATCH = {os.path.join(_TORCH_DIR, name) for name in ("overrides.py", "_tensor.py", "functional.py")}
_READ_BACK = {"item", "tolist", "numpy", "cpu", "cuda", "__float__", "__int__", "__bool__", "__index__", "__array__"}
_MOVES = {"to", "copy_"}
_HOST_DATA = {"tensor", "as_tensor", "asarray"}
_FACTORIES = {"zeros", "ones", "full", "empty", "arange", "range", "linspace", "logspace", "eye", "rand", "randn",
              "randint", "randperm", "scalar_tensor"}
_INDEXING = {"__getitem__", "__setitem__", "index_select", "index_put_", "index_put", "index_add_", "index_copy_",
             "index_fill_", "scatter_", "scatter_add_", "gather", "take"}


def _caller() -> tuple[str, int, str] | None:
    """Who made the call: the first frame outside this module and torch's dispatch layer (the Python bodies of
    tensor methods such as Tensor.__array__ hand the call on from there); None when it is torch's own code."""
    frame = sys._getframe(2)
    while frame is not None and (os.path.abspath(frame.f_code.co_filename) == _HERE
                                 or frame.f_code.co_filename in _DISPATCH):
        frame = frame.f_back
    if frame is None or frame.f_code.co_filename.startswith(_TORCH_DIR):
        return None
    return frame.f_code.co_filename, frame.f_lineno, frame.f_code.co_name


def _host_index(value) -> bool:
    if isinstance(value, (np.ndarray, list)):
        return True
    if isinstance(value, tuple):
        return any(_host_index(v) for v in value)
    return False


def _names_a_device(args, kwargs) -> bool:
    values = list(args) + list(kwargs.values())
    return any(isinstance(v, (torch.device, str)) for v in values) or "device" in kwargs


@dataclass
class HostSyncWatch(TorchFunctionMode):
    """Use as `with HostSyncWatch() as watch:` around a fit; `watch.found` lists (loop, what, where)."""

    found: list[tuple[str, str, str]] = field(default_factory=list)
    loops_seen: set[str] = field(default_factory=set)

    def __post_init__(self):
        super().__init__()

    def _record(self, what: str) -> None:
        where = _caller()
        if where is not None:
            file, line, function = where
            self.found.append((current_loop(), what, f"{os.path.relpath(file)}:{line} in {function}"))

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        loop = current_loop()
        if loop is not None:
            self.loops_seen.add(loop)
            name = getattr(func, "__name__", str(func))
            if name in _READ_BACK:
                self._record(f"Tensor.{name}")
            elif name in _MOVES and _names_a_device(args[1:], kwargs):
                self._record(f"Tensor.{name} to a device")
            elif name in _HOST_DATA:
                self._record(f"torch.{name} from host data")
            elif name in _FACTORIES and "device" not in kwargs:
                self._record(f"torch.{name} without device=")
            elif name in _INDEXING and _host_index(args[1:]):
                self._record(f"{name} with a host array index")
        return func(*args, **kwargs)

    def _profile(self, frame, event, arg):
        if event == "c_call" and arg is torch.from_numpy and current_loop() is not None:
            self._record("torch.from_numpy")

    def __enter__(self):
        self._previous = sys.getprofile()
        sys.setprofile(self._profile)
        return super().__enter__()

    def __exit__(self, *exc):
        sys.setprofile(self._previous)
        return super().__exit__(*exc)
