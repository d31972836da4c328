"""The one logging set-up of every process's main(): under systemd (journald reads stderr) each line starts with its
syslog priority `<N>` and carries no timestamp of its own (the journal stamps it); elsewhere lines start with a
timestamp. The level comes from `--log-level` or the ROADLOG_LOG_LEVEL the daemon passes to its processes.
`kill -USR1 PID` makes a process write every thread's Python stack to its stderr (the journal): what a process
that does not stop, or does not answer, is doing."""

from __future__ import annotations

import faulthandler
import logging
import os
import signal
import sys
from collections.abc import Mapping

LOG_LEVEL_ENV = "ROADLOG_LOG_LEVEL"  # the daemon's --log-level, inherited by every process it starts
LEVELS = ("debug", "info", "warning", "error")
DEFAULT_LEVEL = "info"
# logging level -> syslog priority (sd-daemon(3): `<N>` at the start of a line sets that line's priority)
PRIORITIES = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}


def under_journal(env: Mapping[str, str] = os.environ) -> bool:
    """True when systemd started us (INVOCATION_ID) or stderr goes to the journal (JOURNAL_STREAM)."""
    return bool(env.get("JOURNAL_STREAM") or env.get("INVOCATION_ID"))


def priority(levelno: int) -> int:
    """The syslog priority of a logging level (a custom level takes that of the standard one below it)."""
    return next((p for level, p in sorted(PRIORITIES.items(), reverse=True) if levelno >= level), 7)


class JournalFormatter(logging.Formatter):
    """`<N>process: message`, every line of a multi-line message (a traceback) prefixed: journald takes each
    line as an entry of its own."""

    def __init__(self, process: str):
        super().__init__(f"{process}: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


def level_from(name: str | None, env: Mapping[str, str] = os.environ) -> int:
    """The logging level named (else ROADLOG_LOG_LEVEL, else info); an unknown name is a ValueError."""
    text = (name or env.get(LOG_LEVEL_ENV) or DEFAULT_LEVEL).lower()
    if text not in LEVELS:
        raise ValueError(f"log level {text!r}: choose from {', '.join(LEVELS)}")
    return getattr(logging, text.upper())


def setup_logging(process: str, level: str | None = None) -> None:
    """Route the root logger to stderr for process `process`, replacing any earlier handler (one set-up)."""
    try:
        chosen = level_from(level)
    except ValueError as exc:  # a bad ROADLOG_LOG_LEVEL must not stop a process: say so, log at info
        chosen = logging.INFO
        print(f"{process}: {exc}; logging at info", file=sys.stderr)
    handler = logging.StreamHandler(sys.stderr)
    if under_journal():
        handler.setFormatter(JournalFormatter(process))
        sys.excepthook = _logged_crash  # a crash's traceback at critical priority, not as info lines
    else:
        handler.setFormatter(logging.Formatter(f"%(asctime)s {process} %(levelname)s %(message)s"))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(chosen)
    _stacks_on_sigusr1()


def _stacks_on_sigusr1() -> None:
    """SIGUSR1 writes every thread's stack to stderr; to the process's own fd 2 where sys.stderr is not a file (a
    test's capture)."""
    for stream in (sys.stderr, sys.__stderr__):
        try:
            faulthandler.register(signal.SIGUSR1, file=stream, all_threads=True)
            return
        except (AttributeError, ValueError, OSError):  # no fileno (io.UnsupportedOperation is both), or None
            continue


def _logged_crash(kind, value, traceback) -> None:
    if issubclass(kind, KeyboardInterrupt):
        sys.__excepthook__(kind, value, traceback)
        return
    logging.getLogger().critical("crashed: %s: %s", kind.__name__, value, exc_info=(kind, value, traceback))


def error_line(text: str) -> str:
    """`error: text` as a line for stderr, with the error priority under the journal (outside logging); a text of
    several lines (an invalid config: a line per bad key) has the priority on each, as JournalFormatter does."""
    lines = f"error: {text}".splitlines()
    return "\n".join("<3>" + line for line in lines) if under_journal() else "\n".join(lines)
