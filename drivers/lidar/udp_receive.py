"""Receiving a Lidar's UDP datagrams in batches: a socket with kernel arrival times and overflow counts, and one
(N, row bytes) buffer filled with what arrives within a batch period, each row with its real length and arrival
time; and the drivers' serve loop (`serve_batches`: health on a period, batches as they arrive). Shared by the
Ouster driver and the vendor packet driver."""

from __future__ import annotations

import select
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from daemon.spine.health import HealthCounters

# Linux socket options Python's socket module does not name (asm-generic/socket.h).
SO_RCVBUFFORCE = 33  # SO_RCVBUF beyond net.core.rmem_max, with CAP_NET_ADMIN
SO_TIMESTAMPNS = 35  # kernel receive time (CLOCK_REALTIME) as ancillary data
SO_RXQ_OVFL = 40  # datagrams the kernel dropped because the receive buffer was full, as ancillary data
_ANCILLARY_BYTES = socket.CMSG_SPACE(16) + socket.CMSG_SPACE(4)
_TIMESPEC = struct.Struct("=qq")
_DROP_COUNT = struct.Struct("=I")


class SocketStats(Protocol):
    kernel_drops: int  # the socket's overflow count (SO_RXQ_OVFL), as last reported by the kernel
    socket_errors: int


@dataclass
class ReceiveBuffer:
    """Rows of one batch of datagrams: bytes (truncated to the row), real lengths, arrival times."""

    rows: np.ndarray  # (N, packet_size) uint8
    sizes: np.ndarray  # (N,) int64, the datagram's real length (MSG_TRUNC)
    arrival_ns: np.ndarray  # (N,) int64, host CLOCK_MONOTONIC at arrival
    views: list[memoryview] = field(repr=False)

    @classmethod
    def allocate(cls, capacity: int, row_bytes: int) -> ReceiveBuffer:
        rows = np.zeros((capacity, row_bytes), np.uint8)
        return cls(rows, np.zeros(capacity, np.int64), np.zeros(capacity, np.int64), [memoryview(r) for r in rows])


def open_lidar_socket(bind_address: str, port: int, receive_buffer_bytes: int) -> tuple[socket.socket, int]:
    """A non-blocking UDP socket bound to (bind_address, port) with kernel arrival times and overflow
    counts, and the receive buffer the kernel granted (SO_RCVBUFFORCE when allowed, else SO_RCVBUF,
    which the kernel caps at net.core.rmem_max)."""
    sock = socket.socket(socket.AF_INET6 if ":" in bind_address else socket.AF_INET, socket.SOCK_DGRAM)
    try:
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, receive_buffer_bytes)
        except PermissionError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer_bytes)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
        sock.bind((bind_address, port))
    except OSError as exc:
        sock.close()
        raise OSError(exc.errno, f"cannot listen for lidar packets on UDP {bind_address}:{port}: {exc.strerror}") \
            from None
    sock.setblocking(False)
    return sock, sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)


def report_short_buffer(granted: int, asked: int, health: HealthCounters) -> None:
    """A receive buffer smaller than the config asks for, as the health's last error."""
    if granted < asked:
        health.last_error = f"receive buffer {granted} B granted of {asked} B asked (raise net.core.rmem_max)"


def receive_queued(sock: socket.socket, buf: ReceiveBuffer, start: int, mono_minus_real_ns: int,
                    stats: SocketStats, health: HealthCounters) -> int:
    """Receive the datagrams already queued into rows start.. of `buf`; returns the rows filled."""
    for i in range(start, len(buf.views)):
        try:
            size, ancillary, _, _ = sock.recvmsg_into([buf.views[i]], _ANCILLARY_BYTES, socket.MSG_TRUNC)
        except BlockingIOError:
            return i
        except OSError as exc:
            stats.socket_errors += 1
            health.count_error(f"receiving: {exc}")
            return i
        arrival_ns = 0
        for level, kind, data in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
                seconds, nanoseconds = _TIMESPEC.unpack_from(data)
                arrival_ns = seconds * 1_000_000_000 + nanoseconds + mono_minus_real_ns
            elif level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(data) >= _DROP_COUNT.size:
                stats.kernel_drops = _DROP_COUNT.unpack_from(data)[0]
        buf.sizes[i] = size
        buf.arrival_ns[i] = arrival_ns or time.monotonic_ns()
    return len(buf.views)


def gather_batch(sock: socket.socket, buf: ReceiveBuffer, batch_period_s: float, stats: SocketStats,
                  health: HealthCounters) -> int:
    """Rows of `buf` filled with what arrives within batch_period_s (or until it is full)."""
    deadline = time.monotonic() + batch_period_s
    mono_minus_real_ns = time.monotonic_ns() - time.time_ns()
    n = receive_queued(sock, buf, 0, mono_minus_real_ns, stats, health)
    while n < len(buf.views):
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        time.sleep(remaining)  # let datagrams gather in the kernel's buffer
        n = receive_queued(sock, buf, n, mono_minus_real_ns, stats, health)
    return n


def serve_batches(sock: socket.socket, buf: ReceiveBuffer, batch_period_s: float, on_batch: Callable[[int], None],
                  report_health: Callable[[], None], stop: threading.Event, stats: SocketStats, health: HealthCounters,
                  health_period_s: float, idle_wait_s: float,
                  others: dict[socket.socket, Callable[[], None]] | None = None) -> None:
    """Until `stop` is set: health reported at once and then every `health_period_s`; each batch gathered on `sock`
    (gather_batch) given to `on_batch` as its row count; each of `others` handled when it is readable, before the
    batch. Waits at most `idle_wait_s` at a time, so that `stop` is seen."""
    poller = select.poll()
    handlers = {s.fileno(): handle for s, handle in (others or {}).items()}
    for fd in (sock.fileno(), *handlers):
        poller.register(fd, select.POLLIN)
    report_health()
    next_health = time.monotonic() + health_period_s
    while not stop.is_set():
        now = time.monotonic()
        if now >= next_health:
            report_health()
            next_health = max(next_health + health_period_s, now)
        ready = {fd for fd, _ in poller.poll(max(0, round(1000 * min(idle_wait_s, next_health - now))))}
        for fd in ready & handlers.keys():
            handlers[fd]()
        if sock.fileno() not in ready:
            continue
        n = gather_batch(sock, buf, batch_period_s, stats, health)
        if n:
            on_batch(n)
