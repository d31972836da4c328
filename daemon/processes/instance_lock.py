"""One daemon per bus and per data folder: lock files held with `flock`, which the kernel releases when the last
process holding them dies (the daemon and the children it passes them to), so a killed daemon's lock never blocks.
A daemon that ends cleanly removes its lock files; one that was killed leaves them, unlocked.

A second `roadlog run`/`replay` on the same bus prefix would unlink the first one's rings; on the same data folder
its recorder would "recover" the first one's open segment. It is refused with one line and EXIT_ALREADY_RUNNING.
"""

from __future__ import annotations

import fcntl
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from daemon.bus.pubsub import SHM_DIR
from daemon.spine.config import CarConfig, ConfigError

EXIT_ALREADY_RUNNING = 3  # `roadlog run`/`replay` exit status when another daemon holds the bus or the data folder
LOCK_WAIT_S = 3.0  # a killed daemon's children hold its locks until they die too (SIGKILLed with it: milliseconds)
DATA_LOCK = ".roadlog.lock"


class AlreadyRunning(Exception):
    """Another daemon holds one of this run's locks; the message is the one line to print."""


def bus_lock_path(config: CarConfig) -> Path:
    """Beside the rings, outside their `<prefix>.*` names (which a starting daemon removes)."""
    return Path(SHM_DIR) / f"{config.bus.shm_prefix}-daemon.lock"


def _holder(fd: int) -> int | None:
    """The pid of the daemon that took the lock (written in the file), None when unreadable."""
    text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    return int(text) if text.isdigit() else None


def _alive(pid: int | None) -> bool:
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _same_file(path: Path, fd: int) -> bool:
    """Whether the locked file is still the one at `path` (a daemon ending cleanly removes its lock file)."""
    try:
        return os.stat(path).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
        return False


def _lock(path: Path, what: str, wait_s: float) -> int:
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise ConfigError(f"cannot open the lock file {path} ({what}): {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            # a live holder is a running daemon: refuse at once; a dead one's children are still going: wait a little
            if _alive(holder) or time.monotonic() >= deadline:
                who = f"pid {holder}" if _alive(holder) else f"the processes of pid {holder}, which is gone"
                raise AlreadyRunning(f"roadlog: another daemon ({who}) already runs on {what} (it holds {path}); "
                                     f"stop it first") from None
            time.sleep(0.05)
            continue
        if _same_file(path, fd):
            break
        os.close(fd)  # locked a file its daemon removed as it ended: lock the one there now
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


@dataclass
class InstanceLocks:
    """The lock files this daemon holds, with their descriptors (which its children inherit)."""

    held: list[tuple[Path, int]] = field(default_factory=list)

    @property
    def fds(self) -> tuple[int, ...]:
        return tuple(fd for _, fd in self.held)

    def release(self) -> None:
        """A clean end (the children are gone): remove the lock files, then let go of them."""
        for path, fd in self.held:
            if _same_file(path, fd):
                os.unlink(path)
            os.close(fd)
        self.held = []


def hold_instance_locks(config: CarConfig, data_folder: Path, wait_s: float = LOCK_WAIT_S) -> InstanceLocks:
    """Lock the bus prefix and the data folder (made if missing) for this daemon, for as long as it runs (and its
    children). AlreadyRunning when another daemon holds either. A data folder that cannot be made is not locked: no
    daemon can write there, and the recorder reports why."""
    locks = InstanceLocks()
    bus = bus_lock_path(config)
    data = data_folder.absolute() / DATA_LOCK
    try:
        locks.held.append((bus, _lock(bus, f"bus prefix {config.bus.shm_prefix!r}", wait_s)))
        try:
            data_folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            return locks
        locks.held.append((data, _lock(data, f"data folder {str(data_folder.absolute())!r}", wait_s)))
    except BaseException:
        for _, fd in locks.held:
            os.close(fd)
        raise
    return locks
