"""The ring file's layout: constants, header words, record sizes, the mapping of an open ring and its creation.

A ring is one file in /dev/shm, mapped by every process (no multiprocessing.shared_memory, whose
resource tracker unlinks segments when an attaching process exits). Layout:

    page 0  header words (u64): magic, layout, capacity, writer pid/start time, retired flag,
            the commit counter, two commit descriptors (head, next_seq, last_pos) and the
            writer's reserve and tail positions
    page 1  reader slots (64 bytes each: pid, process start time, read position, flags)
    page 2+ the data area, `capacity` bytes

Positions are absolute byte counts (never wrap); a position's offset in the data area is
`pos % capacity`. A record is [seq, total, meta_len, bulk_len] (32 bytes), the meta bytes, then
the bulk bytes at the next 64-byte boundary; records are 64-byte aligned and never straddle the

The ring's protocol (daemon.bus.ring_buffer) relies on x86-64 memory ordering, so a ring is only opened on x86-64.
"""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import platform

from daemon.bus.futex import futex_wake_args
from daemon.spine.config import ConfigError

MAGIC = 0x314752494C52524F  # "ORRLIRG1" little-endian, "roadlog ring v1"
LAYOUT = 1
PAGE = 4096
HEADER_BYTES = 2 * PAGE
DATA_OFFSET = HEADER_BYTES
ALIGN = 64
RECORD_HEADER_BYTES = 32
PAD_SEQ = 2**64 - 1
NO_RECORD = 2**64 - 1
MAX_READER_SLOTS = PAGE // 64

# Header word indices (u64). Writer-owned hot words sit on their own cache lines.
W_MAGIC, W_LAYOUT, W_CAPACITY, W_WRITER_PID, W_WRITER_START, W_RETIRED = 0, 1, 2, 3, 4, 5
W_COMMIT = 8
W_DESC = (16, 24)  # each: head, next_seq, last_pos
W_RESERVE = 32
W_TAIL = 40
W_SLOTS = PAGE // 8  # slot i at W_SLOTS + 8 * i: pid, start time, read position, flags
SLOT_LOSSLESS = 1


class RingCorrupted(ValueError):
    """A file at a ring's path whose header or records do not hold together (not a roadlog ring, a torn or
    overwritten header, another program's file): readers raise it instead of looping over nonsense."""


class UnsupportedPlatformError(ConfigError):
    """The bus cannot run on this machine (not x86-64): processes report it like an unusable config."""


def require_x86_64() -> None:
    """Refuse to open a ring anywhere but on x86-64, the only architecture whose memory ordering the ring's
    lock-free protocol is argued for (see daemon.bus.ring_buffer)."""
    machine = platform.machine()
    if machine != "x86_64":
        raise UnsupportedPlatformError(
            f"the shared-memory bus runs only on x86-64 (its lock-free ring relies on x86-64 memory ordering); "
            f"this machine is {machine or 'unknown'!r}")


def align_up(n: int) -> int:
    return (n + ALIGN - 1) & ~(ALIGN - 1)


def record_bytes(meta_len: int, bulk_len: int) -> int:
    """Bytes a record with this meta and bulk takes in the data area (header and alignment included)."""
    return align_up(align_up(RECORD_HEADER_BYTES + meta_len) + bulk_len)


def max_bulk_bytes(capacity: int, meta_len: int) -> int:
    """The largest bulk payload that fits a ring of `capacity` bytes next to `meta_len` meta bytes."""
    return (capacity & ~(ALIGN - 1)) - align_up(RECORD_HEADER_BYTES + meta_len)


def process_start_ticks(pid: int) -> int | None:
    """The process's start time (clock ticks since boot), or None when it is gone or a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return None
    if fields[0] in (b"Z", b"X"):
        return None
    return int(fields[19])


def process_alive(pid: int, start_ticks: int) -> bool:
    return pid != 0 and process_start_ticks(pid) == start_ticks


class RingMapping:
    """The open file, its header mapping (read-write) and its data mapping."""

    def __init__(self, path: str, *, writable_data: bool):
        require_x86_64()
        self.path = path
        self.fd = os.open(path, os.O_RDWR)
        try:
            size = os.fstat(self.fd).st_size
            if size < HEADER_BYTES:
                raise RingCorrupted(f"{path} is not a roadlog ring: {size} B, shorter than a ring's header")
            self.header = mmap.mmap(self.fd, HEADER_BYTES, mmap.MAP_SHARED)
            self.q = memoryview(self.header).cast("Q")
            if self.q[W_MAGIC] != MAGIC or self.q[W_LAYOUT] != LAYOUT:
                raise RingCorrupted(f"{path} is not a roadlog ring (layout {LAYOUT})")
            self.capacity = self.q[W_CAPACITY]
            if self.capacity < PAGE or self.capacity % ALIGN or DATA_OFFSET + self.capacity != size:
                raise RingCorrupted(f"{path}: its header says a data area of {self.capacity} B, the file holds "
                                    f"{size - DATA_OFFSET} B: not a ring this software wrote whole")
            prot = mmap.PROT_READ | (mmap.PROT_WRITE if writable_data else 0)
            self.data = mmap.mmap(self.fd, self.capacity, mmap.MAP_SHARED | mmap.MAP_POPULATE, prot,
                                  offset=DATA_OFFSET)
        except BaseException:
            os.close(self.fd)
            raise
        self.dq = memoryview(self.data).cast("Q")
        self.db = memoryview(self.data)
        self.commit_address = ctypes.addressof(ctypes.c_char.from_buffer(self.header)) + 8 * W_COMMIT
        self.wake_args = futex_wake_args(self.commit_address)

    def check_record(self, pos: int, seq: int, total: int, meta_len: int, bulk_len: int) -> None:
        """Raise RingCorrupted unless the record header read at `pos` (not being overwritten) holds together."""
        bad = total < RECORD_HEADER_BYTES or total % ALIGN or total > self.capacity
        if not bad and seq != PAD_SEQ:
            bad = meta_len > total or bulk_len > total or record_bytes(meta_len, bulk_len) > total
        if bad:
            raise RingCorrupted(f"{self.path}: the record at position {pos} does not hold together (seq {seq}, "
                                f"{total} B, meta {meta_len} B, bulk {bulk_len} B): the ring is damaged")

    def check_overtaken(self) -> None:
        """A reader found its record overwritten: the oldest record (tail) is still in the ring, as the writer moves
        the tail before the reserve (read in the other order here); RingCorrupted if not, or readers would jump to
        the tail and be overtaken there again, forever."""
        reserve = self.q[W_RESERVE]
        tail = self.q[W_TAIL]
        if reserve > tail + self.capacity:
            raise RingCorrupted(f"{self.path}: its reserve ({reserve}) is more than the ring past its oldest record "
                                f"({tail}): the ring is damaged")

    def snapshot(self) -> tuple[int, int, int, int]:
        """(commit, head, next_seq, last_pos) of one consistent commit."""
        q = self.q
        while True:
            c = q[W_COMMIT]
            d = W_DESC[c & 1]
            head, next_seq, last_pos = q[d], q[d + 1], q[d + 2]
            if q[W_COMMIT] == c:
                return c, head, next_seq, last_pos

    def close(self) -> None:
        """Drop this process's mapping; zero-copy views still in use keep the data mapping alive."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def reserve_space(fd: int, size: int, path: str) -> None:
    """Give the file `size` bytes of real pages now: a sparse ring on a /dev/shm that fills later would die by SIGBUS
    at the first page the kernel cannot give, mid-drive and without a message. No room is a ConfigError naming the
    ring and what its file system has free."""
    try:
        os.posix_fallocate(fd, 0, size)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):  # a file system that cannot reserve
            return
        st = os.statvfs(os.path.dirname(path) or ".")
        raise ConfigError(f"cannot reserve {size / 2**20:.1f} MiB for the ring {path} ({exc.strerror}; its file "
                          f"system has {st.f_bavail * st.f_frsize / 2**20:.1f} MiB free of "
                          f"{st.f_blocks * st.f_frsize / 2**20:.1f} MiB): enlarge /dev/shm (Docker: --shm-size) "
                          f"or lower bus.ring_bytes") from None


def create_ring_file(path: str, capacity: int, next_seq: int) -> None:
    """Create an initialized ring file at `path` atomically (FileExistsError if one is there), its space reserved
    (reserve_space)."""
    tmp = f"{path}.creating.{os.getpid()}"
    fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o660)
    try:
        os.ftruncate(fd, DATA_OFFSET + capacity)
        reserve_space(fd, DATA_OFFSET + capacity, path)
        with mmap.mmap(fd, HEADER_BYTES, mmap.MAP_SHARED) as header:
            q = memoryview(header).cast("Q")
            q[W_CAPACITY] = capacity
            q[W_DESC[0] + 1] = next_seq
            q[W_DESC[0] + 2] = NO_RECORD
            q[W_LAYOUT] = LAYOUT
            q[W_MAGIC] = MAGIC
            q.release()
        os.link(tmp, path)
    finally:
        os.close(fd)
        os.unlink(tmp)

