"""A shared-memory ring of variable-size records: one writer, many readers, across processes.

The ring file, its header words and record layout are in daemon.bus.ring_layout.

Writer protocol for one record at [start, end), where start = head or the end of a pad:
  1. advance `tail` past every record that the new bytes will overwrite (those before end - capacity)
  2. store `reserve` = end: readers holding data before reserve - capacity know it may be overwritten
  3. write the pad header, the record header, meta and bulk straight into the mapping
  4. fill the spare commit descriptor (head = end, next_seq, last_pos = start), then store
     commit + 1 (the single store that publishes the record), then wake futex waiters.
Reader protocol (seqlock-style): read the record's header and bytes at `pos`, then reload `reserve`;
if reserve - capacity > pos the bytes may be torn, so the reader jumps to `tail` (the oldest
intact record) and counts the sequence numbers it skipped as lost. A zero-copy view stays readable
after it is returned; `Record.still_valid()` re-runs the check after use.

A writer that dies mid-record leaves reserve > head; the next writer covers [head, reserve) with a
pad record and continues the sequence from the last commit. Readers only ever write their own
reader slot (lossless readers publish how far they have read there; the writer waits for them).

Memory ordering: this relies on x86-64 TSO (stores become visible in program order, loads are not
reordered with other loads) and on aligned 8-byte loads and stores being atomic; every header
access below is a single aligned u64 load or store through a memoryview cast to "Q". Other
architectures would need explicit barriers, so a ring is opened only on x86-64 (ring_layout.require_x86_64).
"""

from __future__ import annotations

import fcntl
import os
import time
from dataclasses import dataclass

import numpy as np

from daemon.bus.futex import futex_wait, futex_wake
from daemon.bus.ring_layout import (
    ALIGN,
    MAX_READER_SLOTS,
    NO_RECORD,
    PAD_SEQ,
    PAGE,
    RECORD_HEADER_BYTES,
    SLOT_LOSSLESS,
    W_COMMIT,
    W_DESC,
    W_RESERVE,
    W_RETIRED,
    W_SLOTS,
    W_TAIL,
    W_WRITER_PID,
    W_WRITER_START,
    RingCorrupted,
    RingMapping,
    align_up,
    create_ring_file,
    max_bulk_bytes,
    process_alive,
    process_start_ticks,
)
from daemon.spine.config import ConfigError

_READ_SPIN_S = 50e-6  # a waiting reader re-checks this long before sleeping: saves a futex round trip
_READ_POLL_SLICE_S = 0.05  # longest single futex wait: bounds how late a reader notices a retired ring
_WRITER_WAIT_MAX_SLEEP_S = 0.0005  # lossless writer's poll for slow readers


def retire(path: str) -> None:
    """Mark a ring as replaced and remove its file; readers waiting on it reopen the path."""
    try:
        m = RingMapping(path, writable_data=False)
    except (FileNotFoundError, ValueError, PermissionError):  # gone, or not a ring: removed if it can be
        _remove_foreign(path, path)
        return
    m.q[W_RETIRED] = 1
    futex_wake(m.wake_args)
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    m.close()


def _remove_foreign(path: str, label: str) -> None:
    """Remove a file at a ring's path that is not a usable ring; one that cannot be removed (another user's, in the
    sticky /dev/shm) is a ConfigError naming it and its owner."""
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    except PermissionError:
        try:
            owner = os.stat(path).st_uid
        except OSError:
            owner = "?"
        raise ConfigError(f"{label}: {path} is not a ring this daemon can use and cannot be removed (it belongs to "
                          f"user id {owner}): remove it, or set another bus.shm_prefix") from None


class RingWriter:
    """The single writer of a ring. Opening it creates the ring or resumes an existing one."""

    def __init__(self, path: str, capacity: int, *, label: str | None = None):
        self.label = label or path
        capacity &= ~(ALIGN - 1)
        if capacity < PAGE:
            raise ValueError(f"{self.label}: ring capacity {capacity} B is below the minimum {PAGE} B")
        self._m = self._open(path, capacity)
        m = self._m
        self.capacity = m.capacity
        self._ring = np.frombuffer(m.data, dtype=np.uint8)
        self._commit, self.head, self.next_seq, self.last_pos = m.snapshot()
        self.reserve, self.tail = m.q[W_RESERVE], m.q[W_TAIL]
        if self.reserve > self.head:
            self._recover()

    def _open(self, path: str, capacity: int) -> RingMapping:
        carried_seq = 0
        while True:
            try:
                m = RingMapping(path, writable_data=True)
            except FileNotFoundError:
                try:
                    create_ring_file(path, capacity, carried_seq)
                except FileExistsError:
                    pass
                continue
            except RingCorrupted:  # not a ring (another program's file, a damaged header): a new ring replaces it
                _remove_foreign(path, self.label)
                continue
            except PermissionError:
                _remove_foreign(path, self.label)
                continue
            fcntl.flock(m.fd, fcntl.LOCK_EX)
            try:
                q = m.q
                pid, start = q[W_WRITER_PID], q[W_WRITER_START]
                if q[W_RETIRED]:
                    m.close()
                    continue
                if process_alive(pid, start):
                    raise RuntimeError(f"{self.label}: the ring already has a live writer (pid {pid})")
                if m.capacity != capacity:
                    carried_seq = m.snapshot()[2]
                    retire(path)
                    m.close()
                    continue
                q[W_WRITER_START] = process_start_ticks(os.getpid()) or 0
                q[W_WRITER_PID] = os.getpid()
                return m
            finally:
                if m.fd >= 0:
                    fcntl.flock(m.fd, fcntl.LOCK_UN)

    def _recover(self) -> None:
        """A previous writer died mid-record: cover [head, reserve) with a pad record and commit it."""
        start = self.head
        if self.tail > start:  # every record before head had already been given up
            self.tail = self.reserve
            self._m.q[W_TAIL] = self.tail
        off = start % self.capacity
        self._m.dq[off >> 3] = PAD_SEQ
        self._m.dq[(off >> 3) + 1] = self.reserve - start
        self._commit_record(self.reserve, self.next_seq, self.last_pos)

    def _commit_record(self, head: int, next_seq: int, last_pos: int) -> None:
        q = self._m.q
        c = self._commit + 1
        d = W_DESC[c & 1]
        q[d], q[d + 1], q[d + 2] = head, next_seq, last_pos
        q[W_COMMIT] = c
        self._commit, self.head, self.next_seq, self.last_pos = c, head, next_seq, last_pos
        futex_wake(self._m.wake_args)

    def _record_total(self, pos: int) -> int:
        return self._m.dq[((pos % self.capacity) >> 3) + 1]

    def _lossless_readers_behind(self, limit: int) -> list[int]:
        """Header word indices of the reader slots whose lossless reader has not read up to `limit`."""
        q = self._m.q
        pids = q[W_SLOTS:W_SLOTS + 8 * MAX_READER_SLOTS:8].tolist()
        return [w for w in (W_SLOTS + 8 * i for i, pid in enumerate(pids) if pid)
                if q[w + 3] & SLOT_LOSSLESS and q[w + 2] < limit]

    def _wait_for_lossless_readers(self, limit: int, timeout_s: float | None) -> None:
        """Block until no live lossless reader still has unread records before position `limit`."""
        if limit <= 0:
            return
        q = self._m.q
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        sleep_s = 0.00002
        while True:
            behind = self._lossless_readers_behind(limit)
            if not behind or all(not process_alive(q[w], q[w + 1]) for w in behind):
                return
            if deadline is not None and time.monotonic() >= deadline:
                furthest = min(q[w + 2] for w in behind)
                raise TimeoutError(f"{self.label}: a lossless reader is still at byte {furthest}, "
                                   f"{limit - furthest} B short of what the next write overwrites")
            time.sleep(sleep_s)
            sleep_s = min(2 * sleep_s, _WRITER_WAIT_MAX_SLEEP_S)

    def write(self, meta: bytes, bulk: object = b"", *, lossless: bool = False,
              timeout_s: float | None = None) -> int:
        """Append one record (meta bytes + bulk bytes-like or numpy array); returns its seq.

        lossless: first wait (up to timeout_s, then TimeoutError) until every live lossless reader
        has read past the bytes this record overwrites.
        """
        bulk_array = bulk if isinstance(bulk, np.ndarray) else None
        bulk_len = bulk_array.nbytes if bulk_array is not None else memoryview(bulk).nbytes
        meta_len = len(meta)
        bulk_off = align_up(RECORD_HEADER_BYTES + meta_len)
        total = align_up(bulk_off + bulk_len)
        cap = self.capacity
        if total > cap:
            raise ValueError(f"{self.label}: a {bulk_len} B payload (+{meta_len} B meta) can never fit "
                             f"the {cap} B ring; the largest payload is {max_bulk_bytes(cap, meta_len)} B")
        head = self.head
        off = head % cap
        pad = cap - off if cap - off < total else 0
        start = head + pad
        end = start + total
        boundary = end - cap
        if lossless:  # a reader already at head loses nothing: only the pad may be overwritten
            self._wait_for_lossless_readers(min(boundary, head), timeout_s)
        q, dq = self._m.q, self._m.dq
        t = self.tail
        while t < boundary and t < head:
            t += self._record_total(t)
        if t < boundary:
            t = start
        if t != self.tail:
            self.tail = t
            q[W_TAIL] = t
        self.reserve = end
        q[W_RESERVE] = end
        if pad:
            dq[off >> 3] = PAD_SEQ
            dq[(off >> 3) + 1] = pad
        seq = self.next_seq
        o = start % cap
        i = o >> 3
        dq[i], dq[i + 1], dq[i + 2], dq[i + 3] = seq, total, meta_len, bulk_len
        db = self._m.db
        db[o + RECORD_HEADER_BYTES:o + RECORD_HEADER_BYTES + meta_len] = meta
        if bulk_len:
            b = o + bulk_off
            if bulk_array is not None:
                dst = self._ring[b:b + bulk_len].view(bulk_array.dtype).reshape(bulk_array.shape)
                np.copyto(dst, bulk_array, casting="no")
            else:
                db[b:b + bulk_len] = memoryview(bulk).cast("B")
        self._commit_record(end, seq + 1, start)
        return seq

    def close(self) -> None:
        """Give up writing (the ring stays for readers and for the next writer)."""
        m = self._m
        if m.fd < 0:
            return
        if m.q[W_WRITER_PID] == os.getpid():
            m.q[W_WRITER_PID] = 0
        self._ring = None
        m.close()

    def __del__(self) -> None:  # a dropped writer must not keep the ring claimed for this process
        if hasattr(self, "_m"):
            self.close()


@dataclass(slots=True)
class Record:
    """One record read from a ring. `bulk` is a read-only view into shared memory unless copied."""

    seq: int
    meta: bytes
    bulk: memoryview | bytes
    pos: int
    _mapping: RingMapping

    def still_valid(self) -> bool:
        """Whether the record's bytes are still intact (call after using a zero-copy `bulk`)."""
        m = self._mapping
        return m.q[W_RESERVE] <= self.pos + m.capacity


class RingReader:
    """One reader of a ring: follows the writer, detects being overtaken and counts what it lost.

    start: "next" (records written from now on), "oldest" (everything still in the ring),
    "latest" (the newest record, then what follows). after_seq (with "oldest"): resume a reader that
    already took every record up to this seq: earlier records are passed over, and records the ring no
    longer holds since then count as lost (ignored when the ring's sequence has not reached it: a new
    ring). lossless: take a reader slot and publish the read position there, so lossless writes wait for
    this reader.
    """

    def __init__(self, path: str, *, start: str = "next", lossless: bool = False, after_seq: int | None = None):
        self._slot: int | None = None  # before anything can fail: __del__ releases it
        if start not in ("next", "oldest", "latest"):
            raise ValueError(f"start must be 'next', 'oldest' or 'latest', not {start!r}")
        if after_seq is not None and start != "oldest":
            raise ValueError("after_seq resumes from the oldest record: start must be 'oldest'")
        self.path = path
        self.lossless = lossless
        self.lost = 0
        self.received = 0
        self.skipped = 0
        self.expected: int | None = None  # seq of the next message this reader should see
        self._attach(RingMapping(path, writable_data=False), start)
        if after_seq is not None and after_seq < self._m.snapshot()[2]:
            self.expected = after_seq + 1  # read() passes over what comes before

    def _attach(self, m: RingMapping, start: str) -> None:
        self._m = m
        self.capacity = m.capacity
        _, head, next_seq, last_pos = m.snapshot()
        if start == "next" or (start == "latest" and last_pos == NO_RECORD):
            self.pos, expected = head, next_seq
        elif start == "latest":
            self.pos, expected = last_pos, next_seq - 1
        else:
            self.pos, expected = self._oldest()
        if self.expected is None or expected < self.expected:
            self.expected = expected  # a fresh ring, or a replaced one whose sequence restarted
        if self.lossless:
            self._claim_slot()

    def _oldest(self) -> tuple[int, int]:
        """(position, seq) of the oldest intact message record (RingCorrupted for records that do not hold
        together or positions no writer could have left)."""
        m = self._m
        cap = m.capacity
        while True:
            _, head, next_seq, _ = m.snapshot()
            pos = m.q[W_TAIL]
            if pos > head or head - pos > cap or pos % ALIGN:
                if m.q[W_RESERVE] > pos + cap and not pos % ALIGN:  # overtaken while reading the header words
                    m.check_overtaken()
                    continue
                raise RingCorrupted(f"{self.path}: its oldest record ({pos}) and its head ({head}) are more than "
                                    f"the ring apart: the ring is damaged")
            while pos < head:
                i = (pos % cap) >> 3
                seq, total, meta_len, bulk_len = m.dq[i], m.dq[i + 1], m.dq[i + 2], m.dq[i + 3]
                if m.q[W_RESERVE] > pos + cap:
                    m.check_overtaken()
                    break
                m.check_record(pos, seq, total, meta_len, bulk_len)
                if seq != PAD_SEQ:
                    return pos, seq
                pos += total
            else:
                return head, next_seq

    def _claim_slot(self) -> None:
        m = self._m
        q = m.q
        me, my_start = os.getpid(), process_start_ticks(os.getpid()) or 0
        fcntl.flock(m.fd, fcntl.LOCK_EX)
        try:
            for i in range(MAX_READER_SLOTS):
                w = W_SLOTS + 8 * i
                if q[w] == 0 or not process_alive(q[w], q[w + 1]):
                    q[w] = 0
                    q[w + 1], q[w + 2], q[w + 3] = my_start, self.pos, SLOT_LOSSLESS
                    q[w] = me
                    self._slot = w
                    return
        finally:
            fcntl.flock(m.fd, fcntl.LOCK_UN)
        raise RuntimeError(f"{self.path}: all {MAX_READER_SLOTS} lossless reader slots are taken")

    def _release_slot(self) -> None:
        if self._slot is not None:
            self._m.q[self._slot] = 0
            self._slot = None

    def _reopen(self, deadline: float | None) -> bool:
        """Follow a retired ring to its replacement; False when none appeared before the deadline."""
        while True:
            try:
                m = RingMapping(self.path, writable_data=False)
            except (FileNotFoundError, ValueError):
                if deadline is not None and time.monotonic() >= deadline:
                    return False
                time.sleep(0.01)
                continue
            self._release_slot()
            self._m.close()
            self._attach(m, "oldest")
            return True

    def read(self, timeout_s: float | None = None, *, copy: bool = False) -> Record | None:
        """The next record, waiting up to timeout_s (None: forever; 0: no wait); None on timeout."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        spin_until = 0.0
        while True:
            m = self._m
            q = m.q
            if self._slot is not None and q[self._slot + 2] != self.pos:
                q[self._slot + 2] = self.pos
            commit, head, _, _ = m.snapshot()
            pos = self.pos
            if pos >= head:
                if q[W_RETIRED]:
                    if self._reopen(deadline):
                        continue
                    return None
                remaining = _READ_POLL_SLICE_S if deadline is None else deadline - time.monotonic()
                if remaining <= 0:
                    return None
                now = time.perf_counter()
                if not spin_until:
                    spin_until = now + _READ_SPIN_S
                if now >= spin_until:
                    futex_wait(m.commit_address, commit, min(remaining, _READ_POLL_SLICE_S))
                continue
            loaded = self._load(m, pos, copy)
            if loaded is None:  # overtaken: the writer has overwritten this record
                m.check_overtaken()
                self.pos = q[W_TAIL]
                continue
            seq, total, meta, bulk = loaded
            if seq == PAD_SEQ or seq < self.expected:  # padding, or taken before a resume (after_seq)
                self.pos = pos + total
                continue
            if seq > self.expected:
                self.lost += seq - self.expected
            self.expected = seq + 1
            self.received += 1
            self.pos = pos + total
            return Record(seq, meta, bulk, pos, m)

    @staticmethod
    def _load(m: RingMapping, pos: int, copy: bool) -> tuple[int, int, bytes, memoryview | bytes] | None:
        """(seq, total, meta, bulk) of the record at `pos`; None if it was overwritten while being read."""
        cap = m.capacity
        if pos % ALIGN:
            raise RingCorrupted(f"{m.path}: a record position ({pos}) off the 64-byte grid: the ring is damaged")
        off = pos % cap
        i = off >> 3
        dq, q = m.dq, m.q
        seq, total, meta_len, bulk_len = dq[i], dq[i + 1], dq[i + 2], dq[i + 3]
        if q[W_RESERVE] > pos + cap:
            return None
        m.check_record(pos, seq, total, meta_len, bulk_len)
        if seq == PAD_SEQ:
            return seq, total, b"", b""
        meta_off = off + RECORD_HEADER_BYTES
        meta = bytes(m.db[meta_off:meta_off + meta_len])
        bulk_off = off + align_up(RECORD_HEADER_BYTES + meta_len)
        bulk = m.db[bulk_off:bulk_off + bulk_len]
        if copy:
            bulk = bytes(bulk)
        if q[W_RESERVE] > pos + cap:
            return None
        return seq, total, meta, bulk

    def latest(self, *, copy: bool = True) -> Record | None:
        """The newest record in the ring (again, if this reader already returned it); None if there is none.

        Records between the last one returned and the newest are skipped (counted in `skipped`). A retired ring is
        followed to its replacement, when there is one (else its newest record is returned again).
        """
        while True:
            m = self._m
            if m.q[W_RETIRED] and self._reopen(time.monotonic()):
                continue
            commit, _, next_seq, last_pos = m.snapshot()
            if last_pos == NO_RECORD:
                return None
            if last_pos >= self.pos:
                self.skipped += max(0, next_seq - 1 - self.expected)
                self.pos, self.expected = last_pos, next_seq - 1
                return self.read(0, copy=copy)
            loaded = self._load(m, last_pos, copy)
            if loaded is None:  # the newest record overwritten: only by newer ones, committed since
                if m.snapshot()[0] == commit:
                    raise RingCorrupted(f"{self.path}: its newest record ({last_pos}) is no longer in the ring")
                continue
            seq, _, meta, bulk = loaded
            return Record(seq, meta, bulk, last_pos, m)

    def backlog_bytes(self) -> int:
        """Bytes written but not yet read by this reader."""
        return max(0, self._m.snapshot()[1] - self.pos)

    def close(self) -> None:
        self._release_slot()
        self._m.close()

    def __del__(self) -> None:  # a dropped lossless reader must not hold the writer back
        self._release_slot()

