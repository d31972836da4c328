"""`roadlog ARGS` run as a user runs it, for the tests (a subprocess of the entry point), and the smallest log to
give it."""

import os
import signal
import subprocess
import sys
from pathlib import Path

from daemon.log_format.writer import LogWriter
from daemon.spine.config import CarConfig
from daemon.spine.messages import CanFrame
from daemon.spine.topics import CAN_FRAMES
from tests.daemon_fixtures import REPO


def roadlog(*args: str, cwd: Path = REPO, timeout: float = 120,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`roadlog ARGS` in a session of its own: one that outlives `timeout` is killed with every process it
    started (a daemon's), so a hanging run fails its test without leaving processes behind."""
    env = env or {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM", "INVOCATION_ID")}
    cmd = [sys.executable, "-m", "daemon.commands.cli", *map(str, args)]
    with subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          start_new_session=True) as proc:
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
            raise AssertionError(f"roadlog {' '.join(cmd[3:])} still running after {timeout} s: "
                                 f"{err[-2000:]}") from None
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def can_only_log(path: Path, config: CarConfig, frames: int = 50) -> Path:
    """A log of `frames` CAN frames, 10 ms apart, recorded with `config`: quick to replay (no odometry from it)."""
    with LogWriter(path, config) as writer:
        for i in range(frames):
            writer.write(CAN_FRAMES, CanFrame(sensor_time_ns=i * 10_000_000, arbitration_id=0x100, channel="can0",
                                              data=bytes(8), host_mono_ns=10**9 + i * 10_000_000))
    return path
