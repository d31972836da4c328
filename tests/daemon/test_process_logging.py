"""journald-friendly logging, read from real processes' stderr: under systemd (JOURNAL_STREAM) every line starts with
its syslog priority `<N>` and has no timestamp of its own; elsewhere lines start with one; `--log-level` reaches
every process the daemon starts."""

import importlib
import inspect
import logging
import os
import re
import signal
import subprocess
import sys

from daemon.bus.pubsub import unlink_all
from daemon.spine.process_logging import JournalFormatter, level_from, priority
from daemon.spine.process_table import process_table
from tests.daemon_fixtures import REPO, private_config
from tests.roadlog_cli import can_only_log, roadlog

TIMESTAMP = re.compile(r"\d{4}-\d\d-\d\d[ T]\d\d:\d\d:\d\d")
PRIORITY = re.compile(r"^<([0-7])>")


def _env(journal: bool, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM", "INVOCATION_ID", "ROADLOG_LOG_LEVEL")}
    if journal:
        env["JOURNAL_STREAM"] = "8:123456"  # what systemd sets when stderr is the journal (device:inode)
    return dict(env, **extra)


def _small_log(tmp_path):
    """A config without the mapper (fast to start) and a log of 50 CAN frames recorded with it."""
    config, path = private_config(tmp_path, mapper={"enabled": False}, status={"port": 0})
    log = can_only_log(tmp_path / "drive.mcap", config)
    return config, path, log


def test_under_the_journal_every_line_has_its_priority_and_no_timestamp(tmp_path):
    config, path, log = _small_log(tmp_path)
    try:
        run = roadlog("replay", str(log), "--config", str(path), "--rate", "max", "--output-dir",
                      str(tmp_path / "out"), env=_env(journal=True))
    finally:
        unlink_all(config)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert lines and [line for line in lines if not PRIORITY.match(line)] == []
    assert [line for line in lines if TIMESTAMP.search(line)] == []
    assert any(line.startswith("<6>recorder: ") for line in lines), lines  # info, named by its process
    assert any(line.startswith("<6>replay: replayed 50 messages") for line in lines), lines

    bad = roadlog("status-server", "--config", str(tmp_path / "nope.yaml"), env=_env(journal=True))
    assert bad.returncode == 2 and bad.stderr.startswith("<3>error: ") and len(bad.stderr.splitlines()) == 1


def test_log_level_reaches_every_process_the_daemon_starts(tmp_path):
    config, path, log = _small_log(tmp_path)
    try:
        run = roadlog("replay", str(log), "--config", str(path), "--rate", "max", "--output-dir",
                      str(tmp_path / "out"), "--log-level", "warning", env=_env(journal=True))
    finally:
        unlink_all(config)
    assert run.returncode == 0, run.stderr[-3000:]
    # the recorder and the player log at info on every run: at warning, none of it
    assert [line for line in run.stderr.splitlines() if PRIORITY.match(line) and int(line[1]) > 4] == []
    assert "replayed 50 messages" not in run.stderr
    bad = roadlog("run", "--config", str(path), "--log-level", "chatty", env=_env(journal=False))
    assert bad.returncode == 2 and "--log-level" in bad.stderr


def test_outside_the_journal_lines_start_with_a_timestamp(tmp_path):
    config, path = private_config(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "daemon.commands.cli", "status-server", "--config", str(path),
                             "--port", "0"], cwd=REPO, env=_env(journal=False), stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
        assert "status endpoint on http://" in line and TIMESTAMP.match(line) and not PRIORITY.match(line), line
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        unlink_all(config)


def test_every_line_of_a_traceback_carries_the_priority_and_levels_map_to_syslog():
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        record = logging.getLogger("t").makeRecord("t", logging.ERROR, __file__, 1, "window %d failed", (3,),
                                                   sys.exc_info())
    lines = JournalFormatter("mapper").format(record).splitlines()
    assert lines[0] == "<3>mapper: window 3 failed" and len(lines) > 3
    assert all(line.startswith("<3>") for line in lines) and lines[-1] == "<3>RuntimeError: boom"
    assert [priority(n) for n in (5, 10, 15, 20, 30, 40, 50, 60)] == [7, 7, 7, 6, 4, 3, 2, 2]
    assert level_from(None, {"ROADLOG_LOG_LEVEL": "DEBUG"}) == logging.DEBUG and level_from(None, {}) == logging.INFO
    assert level_from("warning", {"ROADLOG_LOG_LEVEL": "debug"}) == logging.WARNING  # the flag wins


def test_a_crash_under_the_journal_is_logged_at_critical_priority_line_by_line():
    code = ("from daemon.spine.process_logging import setup_logging; setup_logging('mapper'); "
            "[][0]")
    run = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=_env(journal=True), capture_output=True,
                         text=True, timeout=60)
    lines = run.stderr.splitlines()
    assert run.returncode == 1 and lines[0] == "<2>mapper: crashed: IndexError: list index out of range", lines
    assert all(line.startswith("<2>") for line in lines) and lines[-1] == "<2>IndexError: list index out of range"


def test_every_line_of_a_configuration_error_is_at_error_priority_under_the_journal(tmp_path):
    """A config with several bad keys is reported as one `error:` line and a line per key: journald takes each line
    as an entry of its own, so every one carries the error priority (not only the first, the rest at info)."""
    path = tmp_path / "car.yaml"
    path.write_text("vehicle: {frame: 3}\nrecorder: {segment_secs: 60}\n")
    run = roadlog("check-config", str(path), env=_env(journal=True))
    lines = run.stderr.splitlines()
    assert run.returncode == 2 and lines[0].startswith("<3>error: ") and len(lines) > 2, run.stderr
    assert all(line.startswith("<3>") for line in lines), lines
    assert any("vehicle.frame" in line for line in lines) and any("recorder.segment_secs" in line for line in lines)


def test_every_process_the_daemon_runs_sets_up_its_logging_the_one_way(tmp_path):
    """No process keeps a logging set-up of its own (basicConfig with its timestamps): each main() calls
    setup_logging, itself or through the camera processes' or the viewing processes' common main."""
    config, path = private_config(tmp_path)
    modules = {s.module for mode in ("live", "replay") for s in process_table(config, str(path), mode)}
    for name in sorted(modules):
        source = inspect.getsource(importlib.import_module(name))
        assert "basicConfig" not in source, name
        assert "setup_logging(" in source or "camera_process_main(" in source or "viewing_main(" in source, name


def test_sigusr1_writes_every_threads_stack_to_stderr_and_the_process_goes_on():
    """What a process that does not stop is doing: `kill -USR1` dumps its Python stacks (the busy thread's too)
    into its log, and it keeps running."""
    code = ("import threading, time\n"
            "from daemon.spine.process_logging import setup_logging\n"
            "setup_logging('gnss')\n"
            "def spin_in_a_named_function():\n"
            "    while True: time.sleep(0.01)\n"
            "threading.Thread(target=spin_in_a_named_function, daemon=True).start()\n"
            "print('ready', flush=True); time.sleep(2.0)\n"  # one line: the signal may come before the sleep starts
            "print('still here', flush=True)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=_env(journal=False), text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stdout.readline() == "ready\n"
        proc.send_signal(signal.SIGUSR1)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0 and out == "still here\n", (out, err)
    assert "in spin_in_a_named_function" in err and "Current thread" in err and "line 7 in <module>" in err, err
