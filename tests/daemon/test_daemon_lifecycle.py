"""`roadlog run` as systemd sees it: ready and fed while sensors are dead, logging the rest; one daemon at a time (a
second one on the same bus or data folder is refused with one line); a killed daemon's children die with it, and
the next start gets the ports and runs without restarts."""

import os
import random
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import yaml

from daemon.bus.pubsub import unlink_all
from daemon.processes.instance_lock import (
    DATA_LOCK,
    EXIT_ALREADY_RUNNING,
    LOCK_WAIT_S,
    AlreadyRunning,
    bus_lock_path,
    hold_instance_locks,
)
from daemon.spine.config import load_config
from tests.daemon_fixtures import REPO, free_port, http_json, wait_for

LIVE = ("lidar", "gnss", "can", "recorder", "status")  # the sim cameras need a drive to play: they fail (exit 2)


def _write_config(tmp_path: Path, prefix: str, status_port: int, name: str = "car.yaml") -> Path:
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["bus"] = {"shm_prefix": prefix}
    s = data["sensors"]
    s["lidar"].update(port=free_port(socket.SOCK_DGRAM), imu_port=free_port(socket.SOCK_DGRAM),
                      metadata_file=str(REPO / "configs" / s["lidar"]["metadata_file"]))
    s["gnss"]["port"] = str(tmp_path / "no-receiver")  # the driver keeps trying to open it: running, no data
    s["can"].update(dbc_file=str(REPO / "configs" / s["can"]["dbc_file"]),
                    options={"port": random.randint(40000, 49000)})
    data["recorder"]["output_dir"] = str(tmp_path / "logs")
    data["mapper"]["enabled"] = False
    data["status"]["port"] = status_port
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


class Daemon:
    def __init__(self, config_path: Path):
        self.config_path = config_path
        self.port = load_config(config_path).status.port
        self.proc: subprocess.Popen | None = None

    def start(self, cwd: Path = REPO, **kw) -> subprocess.Popen:
        self.proc = subprocess.Popen([sys.executable, "-m", "daemon.commands.cli", "run", "--config",
                                      str(self.config_path)], cwd=cwd, start_new_session=True, **kw)
        return self.proc

    def processes(self) -> dict:
        return http_json(self.port, "/status")[1].get("supervisor", {}).get("processes", {})

    def running(self) -> dict:
        """{name: pid} once every live process runs and the supervisor has published it."""
        procs = self.processes()
        ok = all(procs.get(n, {}).get("state") == "running" for n in LIVE)
        return {n: procs[n]["pid"] for n in LIVE} if ok else {}

    def kill_group(self):
        if self.proc is not None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.proc.wait(30)


def _alive(pid: int) -> bool:
    """Alive and not a zombie (an orphan's zombie waits for whoever reaps orphans here)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.fixture
def daemons(tmp_path):
    prefix = f"t{uuid.uuid4().hex[:10]}"
    path = _write_config(tmp_path, prefix, free_port())
    started: list[Daemon] = []

    def make(config_path=path):
        started.append(Daemon(config_path))
        return started[-1]

    yield make, tmp_path, prefix
    for d in started:
        d.kill_group()
    for p in {d.config_path for d in started}:
        unlink_all(load_config(p))
        bus_lock_path(load_config(p)).unlink(missing_ok=True)  # a killed daemon leaves it (unlocked)


def test_a_second_daemon_is_refused_with_one_line(daemons):
    make, tmp_path, prefix = daemons
    first = make()
    first.start()
    pids = wait_for(first.running, 60, "the first daemon's processes")
    open_segments = wait_for(lambda: list((tmp_path / "logs").glob("*.mcap.open")), 30, "the first daemon's segment")

    # the same config: its bus prefix is taken
    second = make()
    t0 = time.monotonic()
    second.start(stderr=subprocess.PIPE, text=True)
    _, err = second.proc.communicate(timeout=60)
    took = time.monotonic() - t0
    assert second.proc.returncode == EXIT_ALREADY_RUNNING
    assert err.strip().splitlines() == [
        f"roadlog: another daemon (pid {first.proc.pid}) already runs on bus prefix {prefix!r} "
        f"(it holds /dev/shm/{prefix}-daemon.lock); stop it first"]
    assert took < 15, took

    # another bus prefix on the same data folder: the folder is taken (its recorder would take over the segment)
    other = make(_write_config(tmp_path, f"t{uuid.uuid4().hex[:10]}", free_port(), "other.yaml"))
    other.start(stderr=subprocess.PIPE, text=True)
    _, err = other.proc.communicate(timeout=60)
    assert other.proc.returncode == EXIT_ALREADY_RUNNING
    assert err.strip().splitlines() == [
        f"roadlog: another daemon (pid {first.proc.pid}) already runs on data folder {str(tmp_path / 'logs')!r} "
        f"(it holds {tmp_path / 'logs' / '.roadlog.lock'}); stop it first"]

    # the first daemon never noticed: the same processes, its segment still open and growing
    assert first.running() == pids and first.proc.poll() is None
    assert all(p.exists() for p in open_segments)
    assert all(info["restarts"] == 0 for name, info in first.processes().items() if name in LIVE)
    os.killpg(first.proc.pid, signal.SIGTERM)
    assert first.proc.wait(60) == 0
    assert not bus_lock_path(load_config(first.config_path)).exists()  # a clean end removes its lock files
    assert not (tmp_path / "logs" / DATA_LOCK).exists()


def test_a_killed_daemons_children_die_and_the_next_start_runs(daemons):
    make, tmp_path, _ = daemons
    first = make()
    first.start()
    pids = wait_for(first.running, 60, "the daemon's processes")
    os.kill(first.proc.pid, signal.SIGKILL)  # the supervisor alone, as an OOM kill or a crash would
    first.proc.wait(10)
    t0 = time.monotonic()
    wait_for(lambda: not any(_alive(p) for p in pids.values()), 5, "the orphaned children to die")
    orphans_gone_s = time.monotonic() - t0

    # the next start: the stale lock does not block, the ports are free, nothing restarts
    second = make()
    second.start()
    new_pids = wait_for(second.running, 60, "the next start's processes")
    assert not set(new_pids.values()) & set(pids.values())
    time.sleep(3.0)  # a process failing on a port in use would have been restarted by now
    procs = second.processes()
    assert {n: procs[n]["restarts"] for n in LIVE} == dict.fromkeys(LIVE, 0), procs
    assert orphans_gone_s < 1.0, orphans_gone_s
    os.killpg(second.proc.pid, signal.SIGTERM)
    assert second.proc.wait(60) == 0


def test_a_daemon_with_dead_sensors_is_ready_fed_and_logs_the_rest(daemons):
    """No camera can start (exit 2: nothing to play), no GNSS receiver, no Lidar or CAN data: READY=1 still comes
    once the recorder runs (before, it waited for every driver: a start time-out and a restart loop), STATUS= names
    each, WATCHDOG=1 keeps coming, and what there is (the processes' health) is logged."""
    make, tmp_path, _ = daemons
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.settimeout(0.2)
    daemon = make()
    t0 = time.monotonic()
    daemon.start(env=dict(os.environ, NOTIFY_SOCKET=str(tmp_path / "notify.sock"), WATCHDOG_USEC="2000000"))
    received = []

    def drain(seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                received.append((time.monotonic(), sock.recv(4096).decode()))
            except TimeoutError:
                pass

    try:
        wait_for(lambda: drain(0.5) or any(m.startswith("READY=1") for _, m in received), 60, "READY=1")
        # waited for, not the last STATUS= taken: under load that may still be a start-up one
        wait_for(lambda: drain(0.5) or any(_names_every_dead_sensor(m) for _, m in received), 30,
                 "a STATUS= naming every dead sensor")
        written = wait_for(lambda: _recorder_written(daemon), 10, "the recorder's first messages")
        watched_from = time.monotonic()
        drain(3.0)
        daemon_written = _recorder_written(daemon)
    finally:
        sock.close()
    ready_at, ready = next((t, m) for t, m in received if m.startswith("READY=1"))
    assert ready.startswith("READY=1\nSTATUS=recording; degraded: ") and ready_at - t0 < 45
    dogs = [watched_from] + [t for t, m in received if m == "WATCHDOG=1" and t >= watched_from] + [time.monotonic()]
    assert max(b - a for a, b in zip(dogs, dogs[1:], strict=False)) < 2.0, dogs  # WatchdogSec=2 s: never starved
    assert daemon_written > written  # the recorder logs on
    assert daemon.proc.poll() is None


def _names_every_dead_sensor(message: str) -> bool:
    """Whether a notify message's STATUS= names every camera failed with its configuration error, and the Lidar, GNSS
    and CAN drivers running with nothing to read."""
    cameras = ("camera_front_wide", "camera_front_left", "camera_front_right")
    return (message.startswith("STATUS=")
            and all(f"{name} failed (configuration error (exit 2))" in message for name in cameras)
            and all(f"{name} error (0.0 Hz)" in message for name in ("lidar", "gnss", "can")))


def _recorder_written(daemon: Daemon) -> int:
    """Messages the recorder reports written, from /status."""
    written = http_json(daemon.port, "/status")[1].get("recorder", {}).get("written", {})
    return sum(written.values()) if isinstance(written, dict) else 0


def test_instance_locks_refuse_at_once_and_a_clean_release_frees_them(tmp_path):
    """flock conflicts between two opens of the file even in one process: the second hold is refused without the
    wait a dead holder's children get, and once released (files removed) the next hold takes fresh files."""
    config = load_config(_write_config(tmp_path, f"t{uuid.uuid4().hex[:10]}", free_port()))
    folder = tmp_path / "logs" / "not-yet-made"
    first = hold_instance_locks(config, folder)
    try:
        t0 = time.monotonic()
        with pytest.raises(AlreadyRunning, match=rf"another daemon \(pid {os.getpid()}\) already runs on bus prefix"):
            hold_instance_locks(config, folder)
        assert time.monotonic() - t0 < LOCK_WAIT_S / 2
        assert bus_lock_path(config).read_text() == f"{os.getpid()}\n" and (folder / DATA_LOCK).exists()
    finally:
        first.release()
    assert not bus_lock_path(config).exists() and not (folder / DATA_LOCK).exists()
    hold_instance_locks(config, folder).release()


def test_a_relative_output_dir_is_taken_from_the_working_directory_never_beside_the_config(daemons):
    """`recorder.output_dir: logs` in configs/car.yaml, the daemon started in work/: its segments go to work/logs
    (as systemd's WorkingDirectory=/var/lib/roadlog gives /var/lib/roadlog/logs), nothing into configs/."""
    make, tmp_path, prefix = daemons
    (tmp_path / "configs").mkdir()
    path = _write_config(tmp_path / "configs", prefix, free_port())
    data = yaml.safe_load(path.read_text())
    data["recorder"]["output_dir"] = "logs"
    path.write_text(yaml.safe_dump(data))
    work = tmp_path / "work"
    work.mkdir()
    daemon = make(path)
    daemon.start(cwd=work)
    wait_for(lambda: list((work / "logs").glob("*.mcap.open")), 60, "the segment in the working directory's logs/")
    os.killpg(daemon.proc.pid, signal.SIGTERM)
    assert daemon.proc.wait(60) == 0
    assert len(list((work / "logs").glob("roadlog_*.mcap"))) == 1
    assert sorted(p.name for p in (tmp_path / "configs").iterdir()) == ["car.yaml"]
