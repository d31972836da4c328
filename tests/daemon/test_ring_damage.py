"""Damaged or foreign ring files (issue 18 item 8): a reader of a ring whose header or records were overwritten gets
the records that hold together or one clear RingCorrupted, never a hang or another exception; a writer replaces a
file at its path that is not a ring; a file it cannot remove is one configuration error naming its owner."""

from __future__ import annotations

import os
import shutil
import signal
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest

from daemon.bus.ring_buffer import RingReader, RingWriter
from daemon.bus.ring_layout import DATA_OFFSET, PAGE, W_CAPACITY, W_DESC, W_RESERVE, W_TAIL, RingCorrupted
from daemon.spine.config import ConfigError

CASES = 150
CAPACITY = 64 * 1024
HEADER_WORDS = {"capacity": W_CAPACITY, "head": W_DESC[0], "next_seq": W_DESC[0] + 1, "last_pos": W_DESC[0] + 2,
                "head1": W_DESC[1], "reserve": W_RESERVE, "tail": W_TAIL, "commit": 8}


class Hang(Exception):
    pass


def _on_alarm(*_):
    raise Hang


@pytest.fixture
def written_ring(tmp_path):
    """A ring that wrapped several times: ~300 records of 40-3,000 B, the writer gone."""
    path = str(tmp_path / "ring")
    writer = RingWriter(path, CAPACITY)
    rng = np.random.default_rng(0)
    for k in range(300):
        writer.write(struct.pack("<I", k), bytes(rng.integers(0, 256, int(rng.integers(40, 3000)), dtype=np.uint8)))
    writer.close()
    return path


def _damage(source: str, target: str, rng: np.random.Generator) -> str:
    shutil.copy(source, target)
    kind = rng.choice(["header word", "record header", "data bytes", "truncated", "extended"])
    with open(target, "r+b") as f:
        if kind == "header word":
            name = rng.choice(list(HEADER_WORDS))
            values = [0, 1, 63, 2**63, 2**64 - 1, int(rng.integers(0, 2**62))]
            value = values[int(rng.integers(0, len(values)))]
            f.seek(8 * HEADER_WORDS[name])
            f.write(struct.pack("<Q", value))
            kind = f"{kind} {name}={value}"
        elif kind == "record header":  # a record's seq / total / lengths, at a 64-byte boundary of the data
            f.seek(DATA_OFFSET + 64 * int(rng.integers(0, CAPACITY // 64)) + 8 * int(rng.integers(0, 4)))
            values = [0, 7, 64, 2**40, 2**64 - 1]
            f.write(struct.pack("<Q", values[int(rng.integers(0, len(values)))]))
        elif kind == "data bytes":
            f.seek(DATA_OFFSET + int(rng.integers(0, CAPACITY - 512)))
            f.write(bytes(rng.integers(0, 256, 512, dtype=np.uint8)))
        elif kind == "truncated":
            f.truncate(int(rng.integers(0, DATA_OFFSET + CAPACITY)))
        else:
            f.truncate(DATA_OFFSET + CAPACITY + PAGE)
    return kind


def test_damaged_rings_give_records_or_one_clear_error_never_a_hang(written_ring, tmp_path):
    rng = np.random.default_rng(1)
    outcomes = {"read": 0, "RingCorrupted": 0}
    previous = signal.signal(signal.SIGALRM, _on_alarm)
    try:
        for case in range(CASES):
            target = str(tmp_path / f"damaged{case}")
            kind = _damage(written_ring, target, rng)
            signal.setitimer(signal.ITIMER_REAL, 2.0)
            try:
                for start in ("oldest", "latest", "next"):
                    reader = RingReader(target, start=start)
                    for _ in range(400):
                        if reader.read(timeout_s=0) is None:
                            break
                    reader.latest()
                    reader.close()
                outcomes["read"] += 1
            except RingCorrupted as exc:
                assert target in str(exc)
                outcomes["RingCorrupted"] += 1
            except Hang:
                pytest.fail(f"case {case} ({kind}): the reader hung")
            except Exception as exc:  # noqa: BLE001 - anything else is the failure this test looks for
                pytest.fail(f"case {case} ({kind}): {type(exc).__name__}: {exc}")
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
    finally:
        signal.signal(signal.SIGALRM, previous)
    assert outcomes["RingCorrupted"] > 20 and outcomes["read"] > 20, outcomes  # both kinds of damage met


def test_a_writer_replaces_a_file_at_its_path_that_is_not_a_ring(tmp_path):
    path = tmp_path / "ring"
    path.write_bytes(b"another program's file" * 100)
    writer = RingWriter(str(path), CAPACITY)
    writer.write(b"meta", b"bulk")
    reader = RingReader(str(path), start="oldest")
    record = reader.read(timeout_s=0, copy=True)
    assert (bytes(record.meta), bytes(record.bulk)) == (b"meta", b"bulk")
    writer.close()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to make a file of another user")
def test_a_file_of_another_user_that_cannot_be_removed_is_one_config_error():
    """In a sticky folder (as /dev/shm is), another user's file cannot be removed by us: one clear error."""
    folder = Path(tempfile.mkdtemp(prefix="roadlog-sticky-", dir="/tmp"))  # reachable by the other user
    os.chmod(folder, 0o1777)
    path = folder / "ring"
    path.write_bytes(b"x" * 100)
    os.chown(path, 4242, 4242)
    os.chmod(path, 0o600)
    pid = os.fork()
    if pid == 0:  # as an ordinary user, who may not remove or open another's file in a sticky folder
        code = 1
        try:
            os.setgid(4343)
            os.setuid(4343)
            RingWriter(str(path), CAPACITY)
        except ConfigError as exc:
            code = 0 if ("user id 4242" in str(exc) and str(path) in str(exc)) else 2
        except BaseException:  # noqa: BLE001
            code = 3
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    shutil.rmtree(folder)
    assert os.WEXITSTATUS(status) == 0, os.WEXITSTATUS(status)
