"""Linux futex(2) wait and wake on a u32 word in shared memory, by raw syscall (x86-64 only, as is the ring
that uses it: daemon.bus.ring_layout.require_x86_64)."""

from __future__ import annotations

import ctypes

_FUTEX_WAIT, _FUTEX_WAKE = 0, 1  # not FUTEX_PRIVATE: the word is shared between processes
_SYS_FUTEX = 202  # x86-64
_libc = ctypes.CDLL(None, use_errno=True)
_libc.syscall.restype = ctypes.c_long


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def futex_wait(address: int, expected: int, timeout_s: float) -> None:
    """Sleep while the u32 at `address` equals `expected`, at most `timeout_s` (spurious wakes allowed)."""
    ts = _Timespec(int(timeout_s), int((timeout_s % 1.0) * 1e9))
    _libc.syscall(ctypes.c_long(_SYS_FUTEX), ctypes.c_void_p(address), ctypes.c_int(_FUTEX_WAIT),
                  ctypes.c_uint32(expected & 0xFFFFFFFF), ctypes.byref(ts), None, ctypes.c_int(0))


def futex_wake_args(address: int) -> tuple:
    """syscall arguments that wake every waiter on `address` (built once: ctypes objects are slow to make)."""
    return (ctypes.c_long(_SYS_FUTEX), ctypes.c_void_p(address), ctypes.c_int(_FUTEX_WAKE),
            ctypes.c_int(2**31 - 1))


def futex_wake(wake_args: tuple) -> None:
    _libc.syscall(*wake_args)

