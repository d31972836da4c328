"""Readiness sees a stopped driver: the status server (a real process, over HTTP) ages each health message by the
publisher's own stamp, so a SIGSTOPped driver's health grows old and /readyz turns 503; a replaced ring is followed."""

import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

from daemon.bus.pubsub import open_publisher, unlink_all, unlink_topic
from daemon.spine.config import load_config
from daemon.spine.health import HealthCounters
from daemon.spine.process_table import required_drivers
from daemon.spine.topics import health_topic
from tests.daemon_fixtures import REPO, free_port, http_json, private_config, wait_for

ENV = dict(os.environ, PYTHONPATH=f"{REPO / 'tests' / 'fakes'}{os.pathsep}{REPO}")


@pytest.fixture
def status_server(tmp_path):
    """A config with three drivers (one camera, Lidar, GNSS) and its status server, running as a process."""
    _, path = private_config(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["sensors"].update(cameras=data["sensors"]["cameras"][:1], can=None)
    data["status"] = {"port": free_port()}
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    procs = [subprocess.Popen([sys.executable, "-m", "daemon.processes.status_server", "--config", str(path)],
                              env=ENV)]
    port = cfg.status.port

    def start_fake(name):
        procs.append(subprocess.Popen([sys.executable, "-m", "fake_process", "--config", str(path), "--name", name],
                                      env=ENV))
        return procs[-1]

    try:
        wait_for(lambda: http_json(port, "/livez")[0] is not None or None, 30, "the status endpoint")
        yield cfg, port, start_fake
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
                p.kill()
                p.wait()
        unlink_all(cfg)


def test_readyz_fails_for_a_sigstopped_driver_and_recovers(status_server):
    cfg, port, start_fake = status_server
    drivers = {name: start_fake(name) for name in required_drivers(cfg)}
    assert sorted(drivers) == ["camera_front_wide", "gnss", "lidar"]
    wait_for(lambda: http_json(port, "/readyz")[0] == 200, 30, "every driver's health")
    os.kill(drivers["lidar"].pid, signal.SIGSTOP)
    stopped_at = time.monotonic()
    code, body = wait_for(lambda: (r := http_json(port, "/readyz"))[0] == 503 and r, 10, "/readyz to fail")
    took = time.monotonic() - stopped_at
    assert 2.8 <= took < 5.0, took  # max_health_age_s 3 s, less the age of its last health (published every 0.1 s)
    assert len(body["not_ready_because"]) == 1 and body["not_ready_because"][0].startswith("lidar: health is ")
    time.sleep(1.0)
    processes = http_json(port, "/status")[1]["processes"]
    assert processes["lidar"]["health_age_s"] > 3.9  # it grows while the driver is stopped ...
    assert processes["gnss"]["health_age_s"] < 1.0  # ... and only the stopped driver's
    os.kill(drivers["lidar"].pid, signal.SIGCONT)
    wait_for(lambda: http_json(port, "/readyz")[0] == 200, 5, "/readyz after SIGCONT")


def test_board_follows_a_replaced_health_ring(status_server):
    """A publisher on a new ring (the daemon restarted, the status server not): its health is seen, not the old
    ring's last message for ever."""
    cfg, port, _ = status_server

    def publish(detail):
        with open_publisher(cfg, health_topic("gnss")) as pub:
            snap = HealthCounters("gnss").snapshot()
            snap.detail = detail
            pub.publish(snap)

    publish("first ring")
    wait_for(lambda: http_json(port, "/status")[1].get("processes", {}).get("gnss", {}).get("detail") == "first ring",
             10, "the first ring's health")
    unlink_topic(cfg, health_topic("gnss"))  # what a new daemon does to the rings it finds
    publish("second ring")
    wait_for(lambda: http_json(port, "/status")[1]["processes"]["gnss"]["detail"] == "second ring", 5,
          "the replaced ring's health")
