"""The supervisor: starts every process of the table, restarts crashed or hung ones, shuts down cleanly.

Each process runs as `python -m module` (through `child_launch`, which ties its life to the supervisor's). A process
that exits is restarted with exponential backoff (each restart recorded); one whose health topic stops updating for
its `heartbeat_s` is considered hung, killed and restarted. SIGTERM/SIGINT stop everything within each process's
`stop_timeout_s` (SIGTERM first, SIGKILL after, with SIGUSR1 between: its stacks in the log say what held it),
so open log files are closed properly. The supervisor's own state is published as JSON in the `detail` of its
health topic. A dead or crash-looping sensor degrades the daemon, it
never stops it: systemd gets READY=1 once the recorder runs (not waiting for every driver; or once it failed on its
configuration, which no restart mends), a STATUS= line naming what is missing or crash-looping whenever that
changes, and WATCHDOG=1 for as long as this loop runs. A child dies with the supervisor (PR_SET_PDEATHSIG, asked for
by the child: daemon/processes/child_launch.py), however the supervisor ends.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

from daemon.processes import child_launch
from daemon.spine.config import EXIT_CONFIG_ERROR, CarConfig
from daemon.spine.health import HealthCounters
from daemon.spine.process_table import RESTARTS_ENV, ProcessSpec
from daemon.spine.topics import health_topic

MAX_BACKOFF_S = 30.0
CRASH_LOOP_RESTARTS = 3  # this many restarts of one process ...
CRASH_LOOP_WINDOW_S = 60.0  # ... within this window: it is crash-looping (named in STATUS= and /status)
STARTUP_GRACE_S = 20.0
FRESH_HEALTH_S = 3.0  # a process whose newest health is older than this is not (yet) up
SLOW_STOP_S = 2.0  # a process taking longer than this to stop after SIGTERM is named in the log
STACK_DUMP_S = 0.5  # one that does not stop at all is given this long to write its stacks (SIGUSR1) before SIGKILL
log = logging.getLogger(__name__)


def sd_notify(state: str) -> bool:
    """Send one sd_notify datagram (READY=1, WATCHDOG=1, STATUS=...) when NOTIFY_SOCKET is set."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.connect(address)
            sock.sendall(state.encode())
    except OSError as exc:  # systemd's socket gone for a moment: say so, and keep supervising
        print(f"supervisor: sd_notify {state.splitlines()[0]!r} failed: {exc}", file=sys.stderr, flush=True)
        return False
    return True


def watchdog_interval_s() -> float | None:
    """Half of systemd's WatchdogSec (from WATCHDOG_USEC), or None when no watchdog is asked for."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and int(pid) != os.getpid()):
        return None
    return int(usec) / 2e6


@dataclass
class Child:
    spec: ProcessSpec
    popen: subprocess.Popen | None = None
    state: str = "starting"  # starting | waiting | running | backoff | finished | stopped | failed
    restarts: int = 0
    last_exit: int | None = None
    last_reason: str = ""
    started_at: float = 0.0
    next_start_at: float = 0.0
    backoff_s: float = 1.0
    restart_log: list[dict] = field(default_factory=list)


class Supervisor:
    def __init__(self, config: CarConfig, table: list[ProcessSpec], *, env: dict[str, str] | None = None,
                 exit_when_done: bool = False, publish_health: bool = True,
                 startup_grace_s: float = STARTUP_GRACE_S, max_backoff_s: float = MAX_BACKOFF_S):
        self.config = config
        self.children = {spec.name: Child(spec) for spec in table}
        self.env = dict(os.environ, **(env or {}))
        self.exit_when_done = exit_when_done
        self.publish_health = publish_health
        self.startup_grace_s = startup_grace_s
        self.max_backoff_s = max_backoff_s
        self._mapper_told = False
        self.exit_code = 0  # run()'s: not 0 when a replay ends because its player failed
        self.stop_event = threading.Event()
        self.health = HealthCounters("supervisor")
        self.ready_sent = False
        self._subscribers: dict[str, object] = {}
        self._publisher = None
        self._last_health = 0.0
        self._last_watchdog = 0.0
        self._last_status = ""
        self.inherit_fds: tuple[int, ...] = ()  # the daemon's instance locks: its children hold them too

    # --- process control -----------------------------------------------------------------------
    def _start(self, child: Child) -> None:
        cmd = child_launch.command(child.spec.module, list(child.spec.args))
        if child.spec.nice:  # coreutils `nice` execs the process: its pid and parent stay the same
            cmd = ["nice", "-n", str(child.spec.nice), *cmd]
        child.popen = subprocess.Popen(cmd, env=dict(self.env, **{RESTARTS_ENV: str(child.restarts)}),
                                       pass_fds=self.inherit_fds)
        child.state = "running"
        child.started_at = time.monotonic()

    def _schedule_restart(self, child: Child, reason: str) -> None:
        now = time.monotonic()
        if now - child.started_at > 60:  # it ran fine for a while: start the backoff afresh
            child.backoff_s = 1.0
        child.restarts += 1
        child.last_reason = reason
        child.restart_log.append({"at_mono_s": round(now, 3), "reason": reason, "exit": child.last_exit})
        child.restart_log = child.restart_log[-20:]
        child.state = "backoff"
        child.next_start_at = now + child.backoff_s
        child.backoff_s = min(self.max_backoff_s, child.backoff_s * 2)
        log.warning("%s %s; restart #%d in %.1f s", child.spec.name, reason, child.restarts,
                    child.next_start_at - now)

    def _latest_health(self, child: Child):
        """The process's newest DriverHealth on the bus, None when it has published none."""
        from daemon.bus.pubsub import open_subscriber

        topic = health_topic(child.spec.name)
        sub = self._subscribers.get(topic)
        if sub is None:
            try:
                sub = self._subscribers[topic] = open_subscriber(self.config, topic, start="latest")
            except (FileNotFoundError, OSError):
                return None
        return sub.latest(copy=True)

    def _last_health_age_s(self, child: Child) -> float | None:
        """Seconds since the process's newest health message (by its own stamp), None when it has published none."""
        msg = self._latest_health(child)
        if msg is None:
            return None
        return (time.monotonic_ns() - msg.host_mono_ns) / 1e9

    def _check(self, child: Child) -> None:
        now = time.monotonic()
        if (child.state == "backoff" and now >= child.next_start_at) or (
                child.state == "waiting" and self._ready_to_start(child)):
            self._start(child)
            return
        if child.state != "running" or child.popen is None:
            return
        code = child.popen.poll()
        if code is not None:
            child.last_exit = code
            if code == 0 and not child.spec.restart_on_success:
                child.state = "finished"
                return
            if code == EXIT_CONFIG_ERROR:
                child.state = "failed"
                child.last_reason = "configuration error (exit 2): not restarted, see its log"
                log.error("%s %s", child.spec.name, child.last_reason)
                return
            self._schedule_restart(child, f"exited with {code}")
            return
        if child.spec.heartbeat_s > 0 and now - child.started_at > max(self.startup_grace_s, child.spec.heartbeat_s):
            age = self._last_health_age_s(child)
            # no health at all after the grace period, or stale health: hung
            if age is None or age > child.spec.heartbeat_s:
                child.popen.kill()
                child.popen.wait()
                child.last_exit = child.popen.returncode
                self._schedule_restart(child, "hung (no heartbeat)" if age is None else f"hung ({age:.0f} s)")

    def stop_all(self, names: list[str] | None = None) -> None:
        """SIGTERM the given (default: all) running processes, SIGKILL those past their stop timeout."""
        targets = [self.children[n] for n in (names or list(self.children))]
        # stop producers first, consumers (recorder, mapper) after, so they write what they got
        order = sorted(targets, key=lambda c: {"recorder": 1, "mapper": 2, "status": 3}.get(c.spec.name, 0))
        for child in order:
            if child.popen is not None and child.popen.poll() is None:
                child.popen.send_signal(signal.SIGTERM)
                asked = time.monotonic()
                deadline = asked + child.spec.stop_timeout_s
                while child.popen.poll() is None and time.monotonic() < deadline:
                    time.sleep(0.05)
                took = time.monotonic() - asked
                if took > SLOW_STOP_S:  # the journal says what held the daemon's stop
                    log.warning("%s took %.1f s to stop after SIGTERM", child.spec.name, took)
                if child.popen.poll() is None:
                    child.popen.send_signal(signal.SIGUSR1)  # its threads' stacks into its log: what held it
                    time.sleep(STACK_DUMP_S)
                    child.popen.kill()
                    child.popen.wait()
                    child.last_reason = "killed after stop timeout"
                    log.error("%s did not stop within its stop timeout (%.0f s after SIGTERM): killed",
                              child.spec.name, child.spec.stop_timeout_s)
                child.last_exit = child.popen.returncode
            if child.state not in ("finished",):
                child.state = "stopped"

    # --- reporting -----------------------------------------------------------------------------
    def state_document(self) -> dict:
        return {
            "processes": {
                name: {"state": c.state, "pid": c.popen.pid if c.popen else None, "restarts": c.restarts,
                       "last_exit": c.last_exit, "last_reason": c.last_reason, "module": c.spec.module,
                       "restart_log": c.restart_log}
                for name, c in self.children.items()
            },
            "ready_sent": self.ready_sent,
            "degraded": self.degraded(),
        }

    def crash_looping(self) -> list[str]:
        """The processes restarted CRASH_LOOP_RESTARTS times or more within CRASH_LOOP_WINDOW_S."""
        now = time.monotonic()
        return [name for name, c in self.children.items()
                if sum(1 for r in c.restart_log if now - r["at_mono_s"] < CRASH_LOOP_WINDOW_S) >= CRASH_LOOP_RESTARTS]

    def healthy(self) -> bool:
        """No process crash-looping (a degraded daemon is still fed to the watchdog: see `_report`)."""
        return not self.crash_looping()

    def _up(self, child: Child) -> bool:
        age = self._last_health_age_s(child)
        return child.state == "running" and age is not None and age <= FRESH_HEALTH_S

    def recording(self) -> bool:
        """The recorder runs and reports (or this run records nothing): the daemon is ready, degraded or not."""
        recorder = self.children.get("recorder")
        return recorder is None or self._up(recorder)

    def ready(self) -> bool:
        """READY=1: the recorder runs, or cannot (a configuration error, which no restart of the daemon mends)."""
        return self.recording() or self.children["recorder"].state == "failed"

    def degraded(self) -> list[str]:
        """What is missing: each crash-looping process, failed one, required driver not up or not delivering (its
        health not `ok`), with why."""
        looping = set(self.crash_looping())
        problems = []
        for name, c in self.children.items():
            if name in looping:
                problems.append(f"{name} crash-looping ({c.restarts} restarts, last: {c.last_reason})")
            elif c.state == "failed":
                problems.append(f"{name} failed ({c.last_reason.split(':')[0]})")
            elif c.spec.required and not self._up(c):
                problems.append(f"{name} " + ("restarting" if c.state == "backoff" else "not up"))
            elif c.spec.required and (health := self._latest_health(c)) is not None and health.state != "ok":
                problems.append(f"{name} {health.state} ({health.rate_hz:.1f} Hz)")  # runs, but no or too little data
        return problems

    def status_line(self) -> str:
        """systemd's STATUS=: whether it records, and what is missing."""
        problems = self.degraded()
        if "recorder" not in self.children or self.children["recorder"].state == "failed":
            head = "running, not recording"
        else:
            head = "recording" if self.recording() else "starting: waiting for the recorder"
        return f"{head}; degraded: {'; '.join(problems)}" if problems else f"{head}; all processes up"

    def _report(self) -> None:
        now = time.monotonic()
        if now - self._last_health < 1.0:
            return
        self._last_health = now
        status = self.status_line()
        if not self.ready_sent and self.ready():
            self.ready_sent = True
            sd_notify(f"READY=1\nSTATUS={status}")
        elif status != self._last_status:
            sd_notify(f"STATUS={status}")
        self._last_status = status
        interval = watchdog_interval_s()
        if interval and now - self._last_watchdog >= interval:  # this loop runs: the supervisor is alive
            self._last_watchdog = now
            sd_notify("WATCHDOG=1")
        if self.publish_health:
            from daemon.bus.pubsub import open_publisher

            if self._publisher is None:
                self._publisher = open_publisher(self.config, health_topic("supervisor"))
            self.health.count_published()
            snap = self.health.snapshot()
            snap.detail = json.dumps(self.state_document())
            self._publisher.publish(snap)

    # --- main loop -----------------------------------------------------------------------------
    def _ready_to_start(self, child: Child) -> bool:
        """A process that starts after others waits until each of them has published health saying it is up (a
        `starting` health, published while a process loads, keeps it from being taken for hung, no more)."""
        return all((msg := self._latest_health(self.children[name])) is not None and msg.state != "starting"
                   for name in child.spec.start_after if name in self.children)

    def run(self) -> int:
        for child in self.children.values():
            if child.spec.start_after:
                child.state = "waiting"
            else:
                self._start(child)
        while not self.stop_event.is_set():
            for child in self.children.values():
                self._check(child)
            self._report()
            if self.exit_when_done and self._drive_done():
                break
            self.stop_event.wait(0.1)
        sd_notify("STOPPING=1")
        self.stop_all()
        return self.exit_code

    def _drive_done(self) -> bool:
        """Replay mode: once the player finished, let the mapper finish its windows, then stop."""
        replay = self.children.get("replay")
        if replay is not None and (replay.state == "failed" or (replay.state == "backoff" and replay.last_exit)):
            # the player cannot play its logs (exit 2) or crashed: a replay that restarts would play them twice
            self.exit_code = EXIT_CONFIG_ERROR if replay.last_exit == EXIT_CONFIG_ERROR else 1
            log.error("the log player failed (exit %s): stopping the replay", replay.last_exit)
            return True
        if replay is None or replay.state != "finished":
            return False
        mapper = self.children.get("mapper")
        if mapper is None or mapper.state in ("finished", "failed", "stopped"):
            return True
        if mapper.state == "running" and mapper.popen.poll() is None and not self._mapper_told:
            mapper.popen.send_signal(signal.SIGTERM)  # end of drive: finish remaining windows, write the map
            self._mapper_told = True
        return False
