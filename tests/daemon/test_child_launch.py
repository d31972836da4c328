"""child_launch: a supervised process runs its module with its arguments and dies with its parent."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

from daemon.processes import child_launch

ROOT = Path(__file__).resolve().parents[2]


def _env(tmp_path: Path) -> dict[str, str]:
    (tmp_path / "probe_module.py").write_text(textwrap.dedent("""
        import os, sys, time
        if __name__ == "__main__":
            print(os.getpid(), os.getppid(), *sys.argv[1:], flush=True)
            if sys.argv[1:2] == ["sleep"]:
                time.sleep(60)
    """))
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)]))


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


def test_the_module_runs_as_main_with_its_arguments(tmp_path):
    out = subprocess.run(child_launch.command("probe_module", ["a b", "--flag"]), env=_env(tmp_path),
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    pid, ppid, *args = out.stdout.split(maxsplit=2)
    assert int(ppid) == os.getpid()
    assert out.stdout.strip().endswith("a b --flag")
    assert out.stderr == ""  # prctl granted: nothing reported


def test_the_child_dies_when_its_parent_is_killed(tmp_path):
    # an intermediate parent starts the child, prints its pid, then waits; killing it -9 must take the child along
    parent_code = textwrap.dedent("""
        import subprocess, sys, time
        from daemon.processes import child_launch
        child = subprocess.Popen(child_launch.command("probe_module", ["sleep"]), stdout=subprocess.PIPE, text=True)
        print(child.stdout.readline().split()[0], flush=True)
        time.sleep(60)
    """)
    parent = subprocess.Popen([sys.executable, "-c", parent_code], env=_env(tmp_path), stdout=subprocess.PIPE,
                              text=True)
    try:
        child_pid = int(parent.stdout.readline())
        assert _alive(child_pid)
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 5
        while _alive(child_pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not _alive(child_pid), "the child outlived its killed parent"
    finally:
        parent.kill()


def test_a_child_whose_parent_is_already_gone_does_not_start(tmp_path):
    # the pid given as the parent is not our parent: as if the parent had died before the request
    cmd = child_launch.command("probe_module", [], parent_pid=os.getpid() + 10**6)
    out = subprocess.run(cmd, env=_env(tmp_path), capture_output=True, text=True, timeout=30)
    assert out.returncode == child_launch.EXIT_PARENT_GONE
    assert out.stdout == ""
    assert "is gone" in out.stderr
