"""SIGTERM while the main thread holds the stop event's own lock (as it does for a few bytecodes inside
`Event.wait`): a handler that set the event itself would block on that lock forever; the relay sets it once the
lock is free. Also every process's stop goes through it."""

import importlib
import inspect
import subprocess
import sys

from daemon.spine.process_table import process_table
from tests.daemon_fixtures import REPO, private_config

HOLDS_THE_LOCK = """
import os, signal, threading, time
from daemon.spine.stop_signals import set_on_signals
stop = threading.Event()
{install}
with stop._cond:  # the event's lock, held as Event.wait holds it around its wait
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(0.3)  # the handler runs at a bytecode boundary in here
print("handler returned", flush=True)
print("set" if stop.wait(10) else "not set", flush=True)
"""


def _run(install: str, timeout: float = 30) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", HOLDS_THE_LOCK.format(install=install)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def test_a_stop_signal_while_the_main_thread_holds_the_events_lock_still_sets_it():
    assert _run("set_on_signals(stop)").stdout.splitlines() == ["handler returned", "set"]


def test_the_plain_handler_it_replaces_deadlocks_there():
    """The failure this module exists for, reproduced: the process never gets past its handler."""
    try:
        run = _run("signal.signal(signal.SIGTERM, lambda *_: stop.set())", timeout=5)
    except subprocess.TimeoutExpired as exc:
        assert not exc.stdout
        return
    raise AssertionError(f"the plain handler did not deadlock: {run.stdout!r}")


def test_every_process_the_daemon_runs_stops_through_the_relay(tmp_path):
    config, path = private_config(tmp_path)
    modules = {s.module for mode in ("live", "replay") for s in process_table(config, str(path), mode)}
    modules |= {"daemon.processes.daemon_main"}
    for name in sorted(modules):
        source = inspect.getsource(importlib.import_module(name))
        assert "signal.signal(" not in source, name
    shared = {"drivers.camera.camera_process", "mapping.viewing.viewing_process"}  # the cameras' and viewers' main
    for name in sorted(modules | shared):
        source = inspect.getsource(importlib.import_module(name))
        assert "on_signals(" in source or "camera_process_main(" in source or "viewing_main(" in source, name


def test_the_relay_runs_the_callback_with_the_signal(tmp_path):
    code = ("import os, signal, threading\n"
            "from daemon.spine.stop_signals import on_signals\n"
            "got = []\n"
            "done = threading.Event()\n"
            "on_signals(lambda s: (got.append(s), done.set()))\n"
            "os.kill(os.getpid(), signal.SIGINT)\n"
            "print(done.wait(10), got == [int(signal.SIGINT)], flush=True)\n")
    run = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=20)
    assert run.stdout.split() == ["True", "True"], run.stderr
