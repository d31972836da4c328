"""How the vendor decoders' per-point loops are compiled: numba's `njit` on one core (no `parallel`), releasing the
GIL (the mapper decodes scans on several threads), cached on disk where numba finds a writable cache folder (the
source's `__pycache__`, `NUMBA_CACHE_DIR` or the user's cache) and otherwise compiled anew in each process: a
missing or read-only cache folder costs the compile time (`bench/lidar_jit.py`), never a decode."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numba

log = logging.getLogger(__name__)


class CompiledLoop:
    """A function compiled on its first call; called like the function."""

    def __init__(self, func: Callable):
        self._func = func
        try:
            self._dispatcher = numba.njit(cache=True, nogil=True, error_model="numpy")(func)
        except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
            log.info("%s compiled without a cache: %s", func.__qualname__, exc)
            self._dispatcher = numba.njit(nogil=True, error_model="numpy")(func)

    def __call__(self, *args):
        try:
            return self._dispatcher(*args)
        except OSError as exc:  # the cache folder could not be written when the compiled code was saved
            log.info("%s compiled without a cache: %s", self._func.__qualname__, exc)
            self._dispatcher = numba.njit(nogil=True, error_model="numpy")(self._func)
            return self._dispatcher(*args)


def compiled(func: Callable) -> CompiledLoop:
    """Decorator: `func` (numba nopython code) compiled, cached where a cache folder can be written."""
    return CompiledLoop(func)
