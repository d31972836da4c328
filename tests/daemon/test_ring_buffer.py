"""The shared-memory ring: wrap-around, overtaking, zero-copy validity, lossless waits, crash recovery."""

from __future__ import annotations

import functools
import multiprocessing
import os
import platform
import random
import signal
import time
import uuid

import numpy as np
import pytest

from daemon.bus.ring_buffer import RingReader, RingWriter, retire
from daemon.bus.ring_layout import PAGE, UnsupportedPlatformError, max_bulk_bytes, record_bytes
from daemon.spine.config import ConfigError

SPAWN = multiprocessing.get_context("spawn")


@pytest.fixture
def path():
    p = f"/dev/shm/rltest-{uuid.uuid4().hex[:12]}.ring"
    yield p
    retire(p)


@functools.cache
def _pattern_base(n: int) -> np.ndarray:
    return (np.arange(n + 256, dtype=np.uint32) * 7).astype(np.uint8)


def pattern(seq: int, n: int) -> np.ndarray:
    """Payload bytes (7 * i + 13 * seq) mod 256, so torn or misplaced bytes show; a view, no copy."""
    size = max(1 << 20, 1 << max(n - 1, 0).bit_length())
    offset = (13 * 183 * seq) % 256  # 183 = 7^-1 mod 256
    return _pattern_base(size)[offset:offset + n]


def meta_for(seq: int) -> bytes:
    return f"meta-{seq}".encode()


def test_records_of_random_sizes_wrap_around_intact(path):
    rng = random.Random(1)
    writer = RingWriter(path, 16 * PAGE)
    reader = RingReader(path, start="oldest")
    for seq in range(2000):
        n = rng.choice([0, 1, 63, 64, 65, 1000, rng.randrange(0, 30000)])
        assert writer.write(meta_for(seq), pattern(seq, n)) == seq
        record = reader.read(0)
        assert (record.seq, record.meta) == (seq, meta_for(seq))
        assert np.array_equal(np.frombuffer(record.bulk, np.uint8), pattern(seq, n))
    assert reader.read(0) is None
    assert (reader.received, reader.lost) == (2000, 0)


def test_bulk_may_be_bytes_memoryview_or_strided_array(path):
    writer = RingWriter(path, 16 * PAGE)
    reader = RingReader(path)
    image = np.arange(24 * 32 * 3, dtype=np.uint16).reshape(24, 32, 3)
    strided = image[::2, ::3]
    for bulk in (b"abc", memoryview(b"xyz" * 100), image, strided):
        writer.write(b"", bulk)
        got = reader.read(0).bulk
        expected = np.ascontiguousarray(bulk).tobytes() if isinstance(bulk, np.ndarray) else bytes(bulk)
        assert bytes(got) == expected


def test_payload_up_to_capacity_fits_and_larger_says_why(path):
    capacity = 64 * PAGE
    writer = RingWriter(path, capacity, label="topic 'x'")
    reader = RingReader(path)
    largest = max_bulk_bytes(capacity, 5)
    assert record_bytes(5, largest) == capacity
    writer.write(b"12345", pattern(1, largest))
    assert np.array_equal(np.frombuffer(reader.read(0).bulk, np.uint8), pattern(1, largest))
    with pytest.raises(ValueError, match=rf"topic 'x'.*{largest + 1} B payload.*{capacity} B ring"):
        writer.write(b"12345", bytes(largest + 1))


def test_overtaken_reader_counts_exactly_what_it_lost(path):
    writer = RingWriter(path, 16 * PAGE)
    reader = RingReader(path, start="next")
    rng = random.Random(2)
    received = []
    for seq in range(3000):
        writer.write(meta_for(seq), pattern(seq, rng.randrange(0, 5000)))
        if rng.random() < 0.05:  # a slow reader: sometimes drains a few
            for _ in range(rng.randrange(1, 4)):
                record = reader.read(0)
                if record is not None:
                    assert record.meta == meta_for(record.seq)
                    received.append(record.seq)
    while (record := reader.read(0)) is not None:
        received.append(record.seq)
    assert received == sorted(received)
    assert reader.lost > 0
    assert reader.received == len(received)
    assert reader.received + reader.lost == 3000


def test_zero_copy_view_revalidates_after_use(path):
    writer = RingWriter(path, 16 * PAGE)
    reader = RingReader(path)
    writer.write(b"", pattern(0, 25000))
    record = reader.read(0)
    assert record.still_valid()
    writer.write(b"", pattern(1, 25000))
    assert record.still_valid()  # the second record went into free space
    writer.write(b"", pattern(2, 25000))
    assert not record.still_valid()  # this one wrapped over it
    copied = RingReader(path, start="latest").read(0, copy=True)
    assert isinstance(copied.bulk, bytes)


def test_start_positions(path):
    writer = RingWriter(path, 16 * PAGE)
    for seq in range(5):
        writer.write(meta_for(seq))
    assert RingReader(path, start="oldest").read(0).seq == 0
    assert RingReader(path, start="latest").read(0).seq == 4
    assert RingReader(path, start="next").read(0) is None
    reader = RingReader(path, start="oldest")
    for seq in range(5, 9):
        writer.write(meta_for(seq))
    assert reader.latest().seq == 8
    assert reader.latest().seq == 8  # again: still the newest
    assert (reader.skipped, reader.lost, reader.received) == (8, 0, 1)
    assert reader.read(0) is None
    assert RingReader(RingWriter(path + ".empty", 16 * PAGE).label).latest() is None
    retire(path + ".empty")


def test_a_resumed_reader_takes_what_follows_its_last_seq_and_counts_what_is_gone(path):
    writer = RingWriter(path, 4 * PAGE)
    for seq in range(10):
        writer.write(meta_for(seq), pattern(seq, 200))
    resumed = RingReader(path, start="oldest", after_seq=6)  # its previous incarnation took 0..6
    assert [resumed.read(0).seq for _ in range(3)] == [7, 8, 9] and resumed.read(0) is None
    assert resumed.lost == 0 and resumed.received == 3
    for seq in range(10, 300):  # the ring holds ~60 of these: 10.. are overwritten
        writer.write(meta_for(seq), pattern(seq, 200))
    late = RingReader(path, start="oldest", after_seq=9)
    first = late.read(0)
    assert first.seq > 10 and late.lost == first.seq - 10  # 10 .. first-1 are gone, and counted
    assert RingReader(path, start="oldest", after_seq=1000).read(0).seq == first.seq  # not this ring's sequence
    with pytest.raises(ValueError, match="start must be 'oldest'"):
        RingReader(path, start="next", after_seq=3)


def test_read_timeout_returns_none_after_the_timeout(path):
    RingWriter(path, 16 * PAGE)
    reader = RingReader(path)
    t0 = time.monotonic()
    assert reader.read(0.2) is None
    assert 0.19 <= time.monotonic() - t0 < 0.5
    t0 = time.monotonic()
    assert reader.read(0) is None
    assert time.monotonic() - t0 < 0.01


def test_lossless_writer_waits_for_reader_and_times_out(path):
    writer = RingWriter(path, 16 * PAGE)
    reader = RingReader(path, lossless=True)
    sent = 0
    with pytest.raises(TimeoutError, match="lossless reader"):
        while True:
            writer.write(b"", bytes(4000), lossless=True, timeout_s=0.05)
            sent += 1
    assert sent > 5
    while reader.read(0) is not None:
        pass
    assert (reader.received, reader.lost) == (sent, 0)
    writer.write(b"", bytes(4000), lossless=True, timeout_s=0.05)  # room again
    reader.close()  # an unregistered reader no longer holds the writer back
    for _ in range(50):
        writer.write(b"", bytes(4000), lossless=True, timeout_s=0.05)


def test_second_live_writer_is_refused(path):
    writer = RingWriter(path, 16 * PAGE)
    with pytest.raises(RuntimeError, match="live writer"):
        RingWriter(path, 16 * PAGE)
    writer.close()
    RingWriter(path, 16 * PAGE)


@pytest.mark.parametrize("machine", ["aarch64", "armv7l", "riscv64", ""])
def test_the_ring_refuses_to_start_on_anything_but_x86_64(path, monkeypatch, machine):
    writer = RingWriter(path, 16 * PAGE)  # a ring that exists: attaching to it is refused as well
    writer.write(meta_for(0), pattern(0, 100))
    monkeypatch.setattr(platform, "machine", lambda: machine)
    for open_ring in (lambda: RingWriter(path, 16 * PAGE), lambda: RingReader(path, start="oldest"),
                      lambda: RingWriter(path + ".new", 16 * PAGE)):
        with pytest.raises(UnsupportedPlatformError, match=f"only on x86-64.*this machine is {machine or 'unknown'!r}"):
            open_ring()
    assert issubclass(UnsupportedPlatformError, ConfigError)  # processes exit EXIT_CONFIG_ERROR, not retried
    assert not os.path.exists(path + ".new")
    monkeypatch.undo()
    assert RingReader(path, start="oldest").read(0).seq == 0


class _Died(Exception):
    pass


def test_writer_dying_mid_record_is_recovered_by_the_next_writer(path, monkeypatch):
    writer = RingWriter(path, 16 * PAGE)
    reader = RingReader(path, start="oldest")
    for seq in range(10):
        writer.write(meta_for(seq), pattern(seq, 3000))

    def die(*args):
        raise _Died

    monkeypatch.setattr(writer, "_commit_record", die)
    with pytest.raises(_Died):  # bytes written, tail and reserve moved, never committed
        writer.write(meta_for(10), pattern(10, 30000))
    monkeypatch.undo()
    writer.close()
    resumed = RingWriter(path, 16 * PAGE)
    assert resumed.next_seq == 10
    for seq in range(10, 20):
        resumed.write(meta_for(seq), pattern(seq, 3000))
    got = []
    while (record := reader.read(0)) is not None:
        assert np.array_equal(np.frombuffer(record.bulk, np.uint8), pattern(record.seq, 3000))
        got.append(record.seq)
    assert got == sorted(got) and got[-1] == 19
    assert reader.received + reader.lost == 20


def test_capacity_change_replaces_the_ring_and_readers_follow(path):
    writer = RingWriter(path, 16 * PAGE)
    reader = RingReader(path)
    writer.write(meta_for(0))
    writer.close()
    bigger = RingWriter(path, 32 * PAGE)
    assert bigger.capacity == 32 * PAGE and bigger.next_seq == 1
    bigger.write(meta_for(1))
    assert [reader.read(1).seq, reader.read(1).seq] == [0, 1]
    assert reader.lost == 0


# --- real processes ---------------------------------------------------------------------------


def _write_stream(path: str, capacity: int, count: int, size: int, period_s: float, lossless: bool) -> None:
    writer = RingWriter(path, capacity)
    for _ in range(count):
        seq = writer.next_seq
        writer.write(meta_for(seq), pattern(seq, size), lossless=lossless, timeout_s=10)
        time.sleep(period_s)


def _read_stream(path: str, until_seq: int, delay_s: float, lossless: bool, results) -> None:
    """Read until seq `until_seq` or a b"stop" record; report (pid, received, lost, bad, first, last)."""
    reader = RingReader(path, start="oldest", lossless=lossless)
    bad = 0
    seqs = []
    while True:
        record = reader.read(10, copy=True)
        if record is None:
            break
        if record.meta == b"stop":
            seqs.append(record.seq)
            break
        if record.meta != meta_for(record.seq) or not np.array_equal(
                np.frombuffer(record.bulk, np.uint8), pattern(record.seq, len(record.bulk))):
            bad += 1
        seqs.append(record.seq)
        if record.seq >= until_seq:
            break
        time.sleep(delay_s)
    results.put((os.getpid(), reader.received, reader.lost, bad, seqs[:1], seqs[-1:]))


def test_several_reader_processes_one_slow(path):
    RingWriter(path, 32 * PAGE).close()  # create it so readers can attach before the writer runs
    results = SPAWN.Queue()
    readers = [SPAWN.Process(target=_read_stream, args=(path, 399, delay, False, results))
               for delay in (0, 0, 0.02)]
    for p in readers:
        p.start()
    time.sleep(1.0)  # spawn start-up
    writer = SPAWN.Process(target=_write_stream, args=(path, 32 * PAGE, 400, 2000, 0.0005, False))
    writer.start()
    writer.join(30)
    outcomes = [results.get(timeout=30) for _ in readers]
    for p in readers:
        p.join(10)
    for _, received, lost, bad, first, last in outcomes:
        assert bad == 0
        assert first == [0] or lost > 0
        assert last == [399]
        assert received + lost == 400
    assert max(o[2] for o in outcomes) > 0  # the slow reader was overtaken


def test_reader_killed_mid_stream_does_not_block_a_lossless_writer(path):
    RingWriter(path, 16 * PAGE).close()
    results = SPAWN.Queue()
    slow = SPAWN.Process(target=_read_stream, args=(path, 10**9, 0.01, True, results))
    fast = SPAWN.Process(target=_read_stream, args=(path, 299, 0, True, results))
    slow.start()
    fast.start()
    time.sleep(1.0)
    writer = SPAWN.Process(target=_write_stream, args=(path, 16 * PAGE, 300, 3000, 0, True))
    writer.start()
    watcher = RingReader(path, start="oldest")
    while (record := watcher.read(10)) is not None and record.seq < 30:
        pass  # the writer is now paced by the slow reader (the ring holds about 20 records)
    os.kill(slow.pid, signal.SIGKILL)
    writer.join(30)
    assert writer.exitcode == 0  # no TimeoutError: the dead lossless reader was ignored
    _, received, lost, bad, _, last = results.get(timeout=30)
    fast.join(10)
    slow.join(10)
    assert (received, lost, bad, last) == (300, 0, 0, [299])


def test_writer_killed_mid_stream_then_restarted(path):
    big = 4 << 20
    capacity = 8 * big
    RingWriter(path, capacity).close()
    results = SPAWN.Queue()
    reader = SPAWN.Process(target=_read_stream, args=(path, 10**9, 0, False, results))
    reader.start()
    time.sleep(1.0)
    for _ in range(3):  # killed at a random point, mostly inside a 4 MB copy
        writer = SPAWN.Process(target=_write_stream, args=(path, capacity, 10**6, big, 0, False))
        writer.start()
        time.sleep(1.0 + random.random() * 0.3)
        os.kill(writer.pid, signal.SIGKILL)
        writer.join(10)
    probe = RingWriter(path, capacity)
    last_seq = probe.next_seq - 1 + 50
    for _ in range(50):
        seq = probe.next_seq
        probe.write(meta_for(seq), pattern(seq, 1000))
    probe.write(b"stop")
    _, received, lost, bad, first, last = results.get(timeout=30)
    reader.join(10)
    assert bad == 0
    assert last == [last_seq + 1]
    assert received + lost == last_seq + 2
    assert received > 50
