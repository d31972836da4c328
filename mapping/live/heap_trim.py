"""Giving the heap memory a finished mapping window freed back to the system (glibc's malloc_trim)."""

import ctypes
import ctypes.util


def return_freed_memory() -> None:
    """Give the heap memory freed after a window back to the system (glibc's malloc_trim; a no-op elsewhere).

    A default window's working set is ~1 GB here; after it glibc kept ~600 MB of it as free heap in its per-thread
    arenas (RSS 1,160 MB after a window, 545 MB after the trim), and with windows of different sizes and the
    fits' thread pools that free memory grew from window to window in the 10-minute soak."""
    name = ctypes.util.find_library("c")
    try:
        ctypes.CDLL(name).malloc_trim(0)
    except (OSError, AttributeError, TypeError):
        pass
