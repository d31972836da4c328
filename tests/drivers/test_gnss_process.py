"""`python -m drivers.gnss.serial_driver`: the real process on a pseudo-terminal, read back from the bus."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import yaml

from daemon.bus import pubsub
from daemon.spine.config import load_config
from daemon.spine.topics import GNSS_FIX, GNSS_VELOCITY, IMU, health_topic
from tests.drivers.test_gnss_driver import PROBE, PtyReceiver

ROOT = Path(__file__).resolve().parents[2]
DATA = Path("/work/shared/data")
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared sensor recordings not present")


def write_config(tmp_path: Path) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["bus"]["shm_prefix"] = f"t{uuid.uuid4().hex[:12]}"
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_gnss_driver_process_publishes_fixes_velocities_imu_and_health_on_the_bus(tmp_path):
    config_path = write_config(tmp_path)
    car = load_config(config_path)
    receiver = PtyReceiver(tmp_path / "ttyGNSS")
    proc = subprocess.Popen([sys.executable, "-m", "drivers.gnss.serial_driver", "--config", str(config_path),
                             "--port", str(receiver.link)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        health = pubsub.open_subscriber(car, health_topic("gnss"), start="oldest", wait_s=20)
        fixes = pubsub.open_subscriber(car, GNSS_FIX, start="oldest", wait_s=5)
        imu = pubsub.open_subscriber(car, IMU, start="oldest", wait_s=5)
        speeds = pubsub.open_subscriber(car, GNSS_VELOCITY, start="oldest", wait_s=5)
        deadline = time.monotonic() + 15
        while True:  # probe until the driver reports a received frame: its port is open
            assert time.monotonic() < deadline, "the driver never opened the port"
            receiver.write(PROBE)
            report = health.read(timeout_s=1.5, copy=True)
            if report is not None and report.received > 0:
                break
        drive = (DATA / "gnss_pyubx2/pygpsdata-SF-calibration.log").read_bytes()
        receiver.write(drive[:19_997])  # the first 89 epochs, whole frames
        receiver.write((DATA / "gnss_pyubx2/pygpsdata-ESF.log").read_bytes())
        got, samples = [], []
        while len(got) < 89 and (msg := fixes.read(timeout_s=5.0, copy=True)) is not None:
            got.append(msg)
        while len(samples) < 8 and (msg := imu.read(timeout_s=5.0, copy=True)) is not None:
            samples.append(msg)
        velocities = []
        while len(velocities) < 89 and (msg := speeds.read(timeout_s=5.0, copy=True)) is not None:
            velocities.append(msg)
        assert fixes.read(timeout_s=0.2) is None and imu.read(timeout_s=0.2) is None  # nothing more
        assert speeds.read(timeout_s=0.2) is None
        # the receiver's NAV-PVT velocity of each epoch, stamped as its fix, with its speed accuracy
        assert [v.sensor_time_ns for v in velocities] == [m.sensor_time_ns for m in got]
        assert all(abs(c) < 60 for v in velocities for c in v.velocity_enu_mps)
        assert any(abs(v.velocity_enu_mps[0]) + abs(v.velocity_enu_mps[1]) > 1.0 for v in velocities)  # it drives
        assert all(v.covariance_type == 2 and 0 < v.velocity_covariance[0] == v.velocity_covariance[8] < 1
                   for v in velocities)
        assert len(got) == 89
        assert [m.seq for m in got] == list(range(got[0].seq, got[0].seq + len(got)))
        assert all(m.host_mono_ns > 0 and 51.2 < m.latitude_deg < 51.3 for m in got)
        assert [m.sensor_time_ns - got[0].sensor_time_ns for m in got[:3]] == [0, 10**9, 2 * 10**9]
        assert len(samples) == 8 and all(9.0 < m.accel_mps2[2] < 10.5 for m in samples)
        receiver.unplug()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert "gnss driver stopped" in err
        last = None
        while (msg := health.read(timeout_s=0.2, copy=True)) is not None:
            last = msg
        assert last is not None and last.process == "gnss" and last.published == 89 + 89 + 8
    finally:
        if proc.poll() is None:
            proc.kill()
        if receiver.link.is_symlink():
            receiver.unplug()
        pubsub.unlink_all(car)
