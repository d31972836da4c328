"""The supervisor with real child processes: restarts crashed and hung ones, stops all within bounds."""

import json
import os
import socket
import threading
import time

import pytest

from daemon.bus.pubsub import open_subscriber, unlink_all
from daemon.processes.supervisor import Supervisor
from daemon.spine.process_table import ProcessSpec, process_table
from daemon.spine.topics import POSE, health_topic, topic_table
from tests.daemon_fixtures import REPO, private_config

ENV = {"PYTHONPATH": f"{REPO / 'tests' / 'fakes'}{os.pathsep}{REPO}"}


def _spec(name, config_path, behaviour="ok", after=1.0, **kw):
    args = ("--config", str(config_path), "--name", name, "--behaviour", behaviour, "--after", str(after))
    if "marker" in kw:
        args += ("--marker", str(kw.pop("marker")))
    return ProcessSpec(name, "fake_process", args, **kw)


@pytest.fixture
def config(tmp_path):
    cfg, path = private_config(tmp_path)
    yield cfg, path
    unlink_all(cfg)


def _wait_for_health(cfg, names, timeout=30.0):
    """Wait until each named process has published health (it is up, its signal handlers installed)."""
    for name in names:
        sub = open_subscriber(cfg, health_topic(name), start="oldest", wait_s=timeout)
        assert sub.read(timeout_s=timeout) is not None
        sub.close()


def _run_in_thread(supervisor):
    thread = threading.Thread(target=supervisor.run, daemon=True)
    thread.start()
    return thread


def _wait(predicate, timeout=15.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def test_crashed_process_is_restarted_with_backoff_and_recorded(config, tmp_path):
    cfg, path = config
    sup = Supervisor(cfg, [_spec("lidar", path, "crash", after=0.3), _spec("gnss", path)], env=ENV)
    thread = _run_in_thread(sup)
    try:
        assert _wait(lambda: sup.children["lidar"].restarts >= 2)
        lidar = sup.children["lidar"]
        assert lidar.last_exit == 3 and "exited with 3" in lidar.last_reason
        assert sup.children["gnss"].restarts == 0  # the others are unaffected
        # the restarts are published on the supervisor's health topic
        sub = open_subscriber(cfg, health_topic("supervisor"), start="latest", wait_s=5)

        def published_restarts():
            msg = sub.latest()
            return json.loads(msg.detail)["processes"]["lidar"]["restarts"] if msg is not None else 0

        assert _wait(lambda: published_restarts() >= 2, timeout=10)
        sub.close()
        gaps = [b["at_mono_s"] - a["at_mono_s"] for a, b in zip(lidar.restart_log, lidar.restart_log[1:], strict=False)]
        assert all(g > 0.9 for g in gaps)  # backoff, not a tight loop
    finally:
        sup.stop_event.set()
        thread.join(30)


def test_configuration_error_is_not_restarted(config):
    cfg, path = config
    sup = Supervisor(cfg, [_spec("lidar", path, "bad-config", after=0.2), _spec("gnss", path)], env=ENV)
    thread = _run_in_thread(sup)
    try:
        assert _wait(lambda: sup.children["lidar"].state == "failed")
        time.sleep(1.5)
        assert sup.children["lidar"].restarts == 0 and sup.children["lidar"].last_exit == 2
        assert sup.children["gnss"].state == "running"
    finally:
        sup.stop_event.set()
        thread.join(30)


def test_hung_process_is_killed_and_restarted(config):
    cfg, path = config
    spec = _spec("can", path, "hang", after=0.5, heartbeat_s=1.0)
    sup = Supervisor(cfg, [spec], env=ENV, startup_grace_s=1.0)
    thread = _run_in_thread(sup)
    try:
        assert _wait(lambda: sup.children["can"].restarts >= 1, timeout=20)
        assert "hung" in sup.children["can"].last_reason
        assert sup.children["can"].last_exit == -9
    finally:
        sup.stop_event.set()
        thread.join(30)


def test_sigterm_stops_everything_cleanly_within_bounds(config, tmp_path, caplog, capfd):
    cfg, path = config
    marker = tmp_path / "stopped.txt"
    table = [_spec("lidar", path, marker=marker), _spec("recorder", path, marker=marker),
             _spec("gnss", path, "slow-stop", stop_timeout_s=1.0)]
    sup = Supervisor(cfg, table, env=ENV)
    thread = _run_in_thread(sup)
    assert _wait(lambda: all(c.popen is not None for c in sup.children.values()))
    _wait_for_health(cfg, ["lidar", "recorder", "gnss"])
    t0 = time.monotonic()
    sup.stop_event.set()
    thread.join(30)
    assert time.monotonic() - t0 < 8
    lines = marker.read_text().splitlines()
    assert lines == ["lidar stopped cleanly", "recorder stopped cleanly"]  # producers first, recorder after
    assert sup.children["gnss"].last_exit == -9 and "stop timeout" in sup.children["gnss"].last_reason
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == [
        "gnss did not stop within its stop timeout (1 s after SIGTERM): killed"]
    assert all(c.popen.poll() is not None for c in sup.children.values())
    assert "fake_process.py\", line" in capfd.readouterr().err  # the stuck one's stack, written before the kill


def test_replay_mode_ends_when_the_player_is_done(config):
    cfg, path = config
    table = [ProcessSpec("replay", "fake_process", ("--config", str(path), "--name", "replay",
                                                     "--behaviour", "done", "--after", "0.5"),
                         restart_on_success=False), _spec("recorder", path)]
    sup = Supervisor(cfg, table, env=ENV, exit_when_done=True)
    t0 = time.monotonic()
    assert sup.run() == 0
    assert time.monotonic() - t0 < 10
    assert sup.children["replay"].state == "finished" and sup.children["replay"].restarts == 0


@pytest.mark.parametrize(("behaviour", "code"), [("bad-config", 2), ("crash", 1)])
def test_replay_mode_ends_when_the_player_fails(config, behaviour, code):
    """A player that cannot play its logs (exit 2) or crashes ends the replay with its failure, instead of the
    daemon waiting forever (or playing the logs again)."""
    cfg, path = config
    table = [ProcessSpec("replay", "fake_process", ("--config", str(path), "--name", "replay",
                                                     "--behaviour", behaviour, "--after", "0.3"),
                         restart_on_success=False), _spec("recorder", path)]
    sup = Supervisor(cfg, table, env=ENV, exit_when_done=True)
    done = threading.Event()
    result = []
    threading.Thread(target=lambda: (result.append(sup.run()), done.set()), daemon=True).start()
    finished = done.wait(20)
    if not finished:
        sup.stop_event.set()
        done.wait(30)
    assert finished and result == [code]
    assert sup.children["replay"].restarts <= 1 and sup.children["recorder"].state == "stopped"


def test_a_process_starts_after_the_ones_it_waits_for(config):
    cfg, path = config
    player = ProcessSpec("replay", "fake_process", ("--config", str(path), "--name", "replay"),
                         start_after=("recorder",))
    sup = Supervisor(cfg, [player, _spec("recorder", path)], env=ENV)
    thread = _run_in_thread(sup)
    try:
        assert sup.children["replay"].popen is None  # waiting while the recorder comes up
        _wait_for_health(cfg, ["recorder"])
        assert _wait(lambda: sup.children["replay"].state == "running")
        assert sup.children["replay"].started_at > sup.children["recorder"].started_at
    finally:
        sup.stop_event.set()
        thread.join(30)


def test_a_starting_health_keeps_a_process_alive_but_does_not_start_the_ones_waiting_for_it(config):
    cfg, path = config
    player = ProcessSpec("replay", "fake_process", ("--config", str(path), "--name", "replay"),
                         start_after=("mapper",))
    sup = Supervisor(cfg, [player, _spec("mapper", path, "slow-start", after=4.0, heartbeat_s=2.0)], env=ENV,
                     startup_grace_s=1.0)
    thread = _run_in_thread(sup)
    try:
        _wait_for_health(cfg, ["mapper"])  # its first health: "starting"
        time.sleep(3.0)  # past its heartbeat: a starting health is a heartbeat
        assert sup.children["mapper"].restarts == 0 and sup.children["replay"].popen is None
        assert _wait(lambda: sup.children["replay"].state == "running")  # once it says it is up
        assert sup.children["replay"].started_at > sup.children["mapper"].started_at + 4.0
    finally:
        sup.stop_event.set()
        thread.join(30)


def _notify_socket(tmp_path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify.sock")
    sock.bind(path)
    sock.settimeout(0.2)
    return sock, path


def test_degraded_mode_ready_status_and_watchdog_through_a_crash_loop(config, tmp_path, monkeypatch):
    """A required driver that never comes up and crash-loops: READY=1 still comes once the recorder runs, STATUS=
    names the driver, WATCHDOG=1 keeps coming (it stopped for the whole loop before), the other driver runs on."""
    cfg, path = config
    sock, sock_path = _notify_socket(tmp_path)
    monkeypatch.setenv("NOTIFY_SOCKET", sock_path)
    monkeypatch.setenv("WATCHDOG_USEC", "1000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    table = [_spec("lidar", path, "crash", after=0.0, required=True), _spec("gnss", path, required=True),
             _spec("recorder", path)]
    sup = Supervisor(cfg, table, env=ENV, max_backoff_s=2.0)
    t0 = time.monotonic()
    thread = _run_in_thread(sup)
    received = []

    def drain(until):
        while time.monotonic() < until():
            try:
                received.append((time.monotonic(), sock.recv(4096).decode()))
            except TimeoutError:
                pass

    try:
        drain(lambda: t0 + 30 if sup.children["lidar"].restarts < 3 else 0)  # three within a minute: a crash loop
        looping_at = time.monotonic()
        end = looping_at + 4.0
        drain(lambda: end)
        ready = [t for t, m in received if m.startswith("READY=1")]
        assert ready and ready[0] - t0 < 10  # the recorder was up: not waiting for the dead Lidar
        statuses = [m.split("STATUS=", 1)[1] for _, m in received if "STATUS=" in m]
        ready_status = next(m for _, m in received if m.startswith("READY=1")).split("STATUS=", 1)[1]
        assert ready_status.startswith("recording; degraded: lidar ")
        assert any("lidar crash-looping" in m for m in statuses) and "gnss" not in statuses[-1]
        dogs = [t0] + [t for t, m in received if m == "WATCHDOG=1"]
        gaps = [b - a for a, b in zip(dogs, dogs[1:], strict=False)]
        assert dogs[-1] > end - 1.5 and max(gaps) < 1.5, gaps  # fed every 0.5 s, through the crash loop
        assert sup.crash_looping() == ["lidar"] and "lidar crash-looping" in sup.state_document()["degraded"][0]
        assert sup.children["gnss"].restarts == 0 and sup._up(sup.children["gnss"])
        sup.stop_event.set()
        thread.join(30)
        stop_by = time.monotonic() + 5
        drain(lambda: stop_by if not received or received[-1][1] != "STOPPING=1" else 0)
        assert received[-1][1] == "STOPPING=1"
    finally:
        sup.stop_event.set()
        thread.join(30)
        sock.close()


def test_ready_when_the_recorder_cannot_start_on_its_configuration(config, tmp_path, monkeypatch):
    """A recorder refusing its config (exit 2) is not retried, and no restart of the daemon would mend it: READY=1
    comes (a start time-out would only restart the drivers forever), STATUS= says nothing is recorded and why."""
    cfg, path = config
    sock, sock_path = _notify_socket(tmp_path)
    monkeypatch.setenv("NOTIFY_SOCKET", sock_path)
    sup = Supervisor(cfg, [_spec("recorder", path, "bad-config", after=0.0), _spec("gnss", path, required=True)],
                     env=ENV)
    thread = _run_in_thread(sup)
    ready = None
    try:
        deadline = time.monotonic() + 20
        while ready is None and time.monotonic() < deadline:
            try:
                message = sock.recv(4096).decode()
            except TimeoutError:
                continue
            ready = message if message.startswith("READY=1") else None
    finally:
        sup.stop_event.set()
        thread.join(30)
        sock.close()
    assert ready == "READY=1\nSTATUS=running, not recording; degraded: recorder failed (configuration error (exit 2))"


def test_process_table_live_and_replay(config):
    cfg, path = config
    live = process_table(cfg, str(path), "live")
    names = [p.name for p in live]
    assert names[:3] == ["camera_front_wide", "camera_front_left", "camera_front_right"]
    assert {"lidar", "gnss", "can", "recorder", "mapper", "status"} <= set(names)
    assert all(p.required for p in live if p.name.startswith("camera_") or p.name in ("lidar", "gnss", "can"))
    replay = process_table(cfg, str(path), "replay", replay_logs=("a.mcap", "b.mcap"), replay_rate="max")
    assert [p.name for p in replay][0] == "replay" and "lidar" not in [p.name for p in replay]
    assert replay[0].args[-2:] == ("a.mcap", "b.mcap") and not replay[0].restart_on_success
    recorder_args = {rate: next(p for p in process_table(cfg, str(path), "replay", replay_logs=("a.mcap",),
                                                         replay_rate=rate) if p.name == "recorder").args
                     for rate in ("max", "1.0")}
    assert "--lossless" in recorder_args["max"] and "--lossless" not in recorder_args["1.0"]
    assert "--lossless" not in next(p for p in live if p.name == "recorder").args
    # the mapper plans its stop within its stop timeout; a replay's never skips a window
    mapper = {mode: next(p for p in table if p.name == "mapper") for mode, table in (("live", live),
                                                                                     ("replay", replay))}
    assert mapper["live"].stop_timeout_s == 600.0 and "--stop-timeout-s" in mapper["live"].args
    assert mapper["live"].args[mapper["live"].args.index("--stop-timeout-s") + 1] == "600"
    assert "--no-skip" not in mapper["live"].args and "--no-skip" in mapper["replay"].args
    # the log before the map and what shows it (viewing clouds, the live pose)
    assert {p.name: p.nice for p in live if p.nice} == {"lidar_view": 10, "vehicle_pose": 10, "mapper": 10}


def test_every_topic_has_a_process_that_publishes_it(config):
    """No ghosts: each topic's source is a process the daemon runs (live or replay) or the supervisor itself."""
    cfg, path = config
    running = {p.name for mode in ("live", "replay") for p in process_table(cfg, str(path), mode)} | {"supervisor"}
    table = topic_table(cfg)
    assert {name: t.source for name, t in table.items() if t.source not in running} == {}
    assert POSE not in table  # poses come only with imported logs (a log-only channel)


def test_a_process_runs_at_its_cpu_priority(config):
    cfg, path = config
    sup = Supervisor(cfg, [_spec("mapper", path, nice=7), _spec("recorder", path)], env=ENV)
    thread = _run_in_thread(sup)
    try:
        _wait_for_health(cfg, ["mapper", "recorder"])
        mine = os.getpriority(os.PRIO_PROCESS, 0)
        priority = {n: os.getpriority(os.PRIO_PROCESS, sup.children[n].popen.pid) for n in ("mapper", "recorder")}
        assert priority == {"mapper": min(19, mine + 7), "recorder": mine}
    finally:
        sup.stop_event.set()
        thread.join(30)
