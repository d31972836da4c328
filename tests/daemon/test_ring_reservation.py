"""A ring's space is reserved when it is made: on a real small tmpfs (mounted over /dev/shm in a private user and
mount namespace, `unshare -rm`), a ring that does not fit is a one-line ConfigError at creation, and a ring that
fits survives another program filling the tmpfs afterwards (a sparse ring died by SIGBUS there, with no message)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _namespaces_work() -> bool:
    try:
        return subprocess.run(["unshare", "-rm", "true"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


pytestmark = pytest.mark.skipif(not _namespaces_work(), reason="unshare -rm (user + mount namespace) unavailable")


def on_small_shm(script: str, shm_bytes: int = 2 * 1024 * 1024) -> subprocess.CompletedProcess:
    """Run `script` in Python with /dev/shm a fresh tmpfs of `shm_bytes`, seen by it alone."""
    mount = f"mount -t tmpfs -o size={shm_bytes} roadlog-test /dev/shm"
    return subprocess.run(["unshare", "-rm", "sh", "-c", f'{mount} && exec "$0" -c "$1"', sys.executable,
                           textwrap.dedent(script)], cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_a_ring_larger_than_shm_is_a_clear_error_at_creation_not_a_sigbus_mid_drive():
    done = on_small_shm("""
        import os
        from daemon.bus.ring_buffer import RingWriter
        from daemon.spine.config import ConfigError
        try:
            ring = RingWriter("/dev/shm/t.lidar", 4 * 1024 * 1024)  # twice the tmpfs
        except ConfigError as exc:
            print("ConfigError:", exc)
            print("left:", sorted(os.listdir("/dev/shm")))
            raise SystemExit(0)
        for i in range(200):  # write through the whole ring: the pages beyond the tmpfs are touched
            ring.write(b"m", bytes(40_000))
        print("wrote everything")
        """)
    assert done.returncode == 0, f"rc {done.returncode} (SIGBUS is -7): {done.stderr}"
    lines = done.stdout.splitlines()
    assert lines[0].startswith("ConfigError: cannot reserve 4.0 MiB for the ring /dev/shm/t.lidar")
    assert "/dev/shm" in lines[0] and "bus.ring_bytes" in lines[0]
    assert lines[1] == "left: []"  # no half-made ring stays behind


def test_a_ring_that_fits_survives_another_program_filling_shm_afterwards():
    # (the writer's MAP_POPULATE mapping already took the pages when it could; the reservation makes it certain)
    done = on_small_shm("""
        from daemon.bus.ring_buffer import RingWriter
        ring = RingWriter("/dev/shm/t.lidar", 1024 * 1024)
        filled = 0
        try:  # another program takes every page that is left
            with open("/dev/shm/other-program", "wb") as f:
                while True:
                    f.write(bytes(65536)); f.flush(); filled += 65536
        except OSError:
            pass
        for i in range(100):  # 4 MB through the 1 MiB ring: every page of it written
            ring.write(b"m", i.to_bytes(4, "little") * 10_000)
        print("filled", filled, "wrote 100")
        """)
    assert done.returncode == 0, f"rc {done.returncode} (SIGBUS is -7): {done.stderr}"
    assert "wrote 100" in done.stdout
