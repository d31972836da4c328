"""How a supervised process starts: it first ties its life to its parent's, then runs its module.

`python -m daemon.processes.child_launch PARENT_PID SIGNAL MODULE [ARGS...]` asks the kernel for SIGNAL when the
parent dies (prctl PR_SET_PDEATHSIG), exits if the parent is already gone (it died before the request: no signal
would come), then runs MODULE as `__main__` with ARGS, as `python -m MODULE ARGS` would. A killed daemon so leaves
no orphan holding its rings, ports and segments. This is done here, after exec, and not in a `preexec_fn`: the
supervisor has threads, and Python code run between fork and exec in a threaded process can deadlock on a lock
another thread held at the fork. A failed prctl (not Linux, or refused) is reported on stderr and the module runs
all the same: it then outlives a killed parent, as any process does.
"""

from __future__ import annotations

import ctypes
import errno
import os
import runpy
import signal
import sys

PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when the thread that started it dies
EXIT_PARENT_GONE = 1


def command(module: str, args: list[str], *, parent_pid: int | None = None,
            sig: signal.Signals = signal.SIGKILL) -> list[str]:
    """The argv that runs `module` with `args` in a process that gets `sig` when `parent_pid` (default: this
    process) dies."""
    pid = os.getpid() if parent_pid is None else parent_pid
    return [sys.executable, "-m", "daemon.processes.child_launch", str(pid), signal.Signals(sig).name, module, *args]


def die_with_parent(parent_pid: int, sig: signal.Signals) -> str | None:
    """Ask for `sig` when the parent dies; None when granted, else why not. Exits when the parent is gone."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        failed = libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0
        reason = os.strerror(ctypes.get_errno() or errno.EINVAL) if failed else None
    except (OSError, AttributeError) as exc:  # no libc prctl: not Linux
        reason = str(exc)
    if os.getppid() != parent_pid:  # the parent died before the request (we were re-parented)
        sys.stderr.write(f"child_launch: parent {parent_pid} is gone; not starting\n")
        raise SystemExit(EXIT_PARENT_GONE)
    return reason


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 3:
        sys.stderr.write("usage: python -m daemon.processes.child_launch PARENT_PID SIGNAL MODULE [ARGS...]\n")
        raise SystemExit(2)
    parent_pid, sig_name, module, *args = argv
    reason = die_with_parent(int(parent_pid), signal.Signals[sig_name])
    if reason is not None:
        sys.stderr.write(f"child_launch: prctl(PR_SET_PDEATHSIG) failed ({reason}): {module} will outlive a "
                         f"killed parent\n")
    sys.argv = [module, *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
