"""The systemd unit verifies with systemd-analyze and asks for what the daemon needs."""

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "roadlog.service"


def _unit() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str
    parser.read(UNIT)
    return parser


def test_unit_settings():
    service = _unit()["Service"]
    assert service["Type"] == "notify"
    assert service["Restart"] == "on-failure"
    assert int(service["WatchdogSec"]) > 0
    assert service["ExecStart"].split()[1:] == ["run", "--config", "/etc/roadlog/car.yaml"]
    assert "AF_CAN" in service["RestrictAddressFamilies"]
    assert "/dev/shm" in service["ReadWritePaths"]
    assert "dialout" in service["SupplementaryGroups"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="needs Debian's systemd package")
def test_systemd_analyze_verify(tmp_path):
    # verify checks that ExecStart exists: point it at this checkout's roadlog command
    roadlog = Path(sys.executable).with_name("roadlog")
    text = UNIT.read_text().replace("/opt/roadlog/.venv/bin/roadlog", str(roadlog))
    unit = tmp_path / "roadlog.service"
    unit.write_text(text)
    result = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "roadlog.service" not in result.stderr, result.stderr
