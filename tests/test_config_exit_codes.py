"""One exit rule for configuration errors: every process, run for real as `python -m <module>`, meets an unusable
config (bad YAML, an unknown key, an unknown camera, a missing file it needs at start) with one `error: ...` line on
stderr, no traceback, and exit status EXIT_CONFIG_ERROR (which the supervisor does not retry)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
import yaml

from daemon.spine.config import EXIT_CONFIG_ERROR

ROOT = Path(__file__).resolve().parents[1]
SIM_CONFIG = ROOT / "configs" / "sim.yaml"

# Each process module with the arguments it needs besides --config; {tmp} is the test's folder.
PROCESSES = {
    "drivers.camera.camera_driver": ["--camera", "front_wide"],
    "sim.camera_playback": ["--camera", "front_wide"],
    "drivers.lidar.udp_driver": [],
    "drivers.lidar.vendor_udp_driver": [],
    "drivers.gnss.serial_driver": [],
    "drivers.can.can_driver": [],
    "daemon.processes.recorder": ["--output-dir", "{tmp}/out"],
    "daemon.processes.replay": ["{tmp}/drive.mcap"],
    "daemon.processes.status_server": ["--output-dir", "{tmp}/out"],
    "daemon.commands.cli run": ["--output-dir", "{tmp}/out"],  # daemon_main.run_main
    "daemon.commands.cli replay": ["{tmp}/drive.mcap", "--output-dir", "{tmp}/out"],  # daemon_main.replay_main
    "mapping.live.mapping_worker": ["--output-dir", "{tmp}/out"],
    "mapping.offline.reconstruct_command": ["{tmp}/drive.mcap", "--out", "{tmp}/out"],
}


def _bad_yaml(tmp: Path) -> Path:
    path = tmp / "bad.yaml"
    path.write_text("sensors: [cameras: {\n")
    return path


def _unknown_key(tmp: Path) -> Path:
    data = yaml.safe_load(SIM_CONFIG.read_text())
    data["recorder"]["segment_secs"] = 60
    path = tmp / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


BAD_CONFIGS = {"bad YAML": (_bad_yaml, "not valid YAML"), "unknown key": (_unknown_key, "recorder.segment_secs")}


def run_process(module: str, args: list[str], config: Path, tmp: Path) -> subprocess.CompletedProcess:
    argv = [a.replace("{tmp}", str(tmp)) for a in args]
    return subprocess.run([sys.executable, "-m", *module.split(), "--config", str(config), *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def assert_config_error(run: subprocess.CompletedProcess, expected: str) -> None:
    assert run.returncode == EXIT_CONFIG_ERROR, run.stderr[-3000:]
    assert "Traceback" not in run.stderr, run.stderr[-3000:]
    errors = [line for line in run.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, run.stderr[-3000:]
    assert expected in run.stderr, run.stderr[-3000:]


@pytest.mark.parametrize("bad", BAD_CONFIGS)
@pytest.mark.parametrize("module", PROCESSES)
def test_every_process_exits_2_with_one_error_line_on_an_unusable_config(module, bad, tmp_path):
    make, expected = BAD_CONFIGS[bad]
    config = make(tmp_path)
    run = run_process(module, PROCESSES[module], config, tmp_path)
    assert_config_error(run, expected)
    assert str(config) in run.stderr


def _sim_config_elsewhere(tmp: Path) -> Path:
    """The shipped sim config, valid, but in a folder without the files it names (Lidar metadata, DBC)."""
    path = tmp / "car.yaml"
    path.write_text(SIM_CONFIG.read_text())
    return path


@pytest.mark.parametrize("module, args, expected", [
    ("drivers.camera.camera_driver", ["--camera", "rear"], "no camera named 'rear'"),
    ("sim.camera_playback", ["--camera", "rear"], "no camera named 'rear'"),
    ("sim.camera_playback", ["--camera", "front_wide", "--device", "{tmp}/nope.mcap"], "nope.mcap does not exist"),
    ("drivers.lidar.udp_driver", [], "sensors.lidar.metadata_file"),
    ("drivers.can.can_driver", [], "sim_car.dbc"),
    ("daemon.processes.replay", ["{tmp}/nope.mcap"], "no such log file"),
])
def test_a_config_naming_what_is_not_there_exits_2(module, args, expected, tmp_path):
    run = run_process(module, args, _sim_config_elsewhere(tmp_path), tmp_path)
    assert_config_error(run, expected)


def _not_utf8(tmp: Path) -> Path:
    path = tmp / "latin1.yaml"
    path.write_bytes(SIM_CONFIG.read_bytes().replace(b"# every key", "# caf\u00e9: every key".encode("latin-1"), 1))
    return path


def _alias_bomb(tmp: Path) -> Path:
    """A billion laughs (9^9 values) as the camera list: it hung the loader."""
    lines = ['a0: &a0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 9)]
    path = tmp / "bomb.yaml"
    path.write_text("\n".join(lines) + "\nsensors: {cameras: *a8}\n")
    return path


def _recursive_alias(tmp: Path) -> Path:
    path = tmp / "recursive.yaml"
    path.write_text("sensors: &s {cameras: [*s]}\n")
    return path


def _many_values(tmp: Path) -> Path:
    """250,000 plain values (1.5 MB, no alias): PyYAML composed every one (~5 CPU s here, 38 s for 4 MiB) before the
    expansion check refused them as if aliases had made them."""
    path = tmp / "many.yaml"
    path.write_text("sensors:\n  cameras:\n" + "    - 1\n" * 250_000)
    return path


def _deep(tmp: Path) -> Path:
    path = tmp / "deep.yaml"
    path.write_text("sensors: " + "[" * 20_000 + "]" * 20_000 + "\n")
    return path


def _long_integer(tmp: Path) -> Path:
    path = tmp / "long.yaml"
    path.write_text(SIM_CONFIG.read_text().replace("segment_seconds: 60", "segment_seconds: " + "9" * 5000, 1))
    return path


UNREADABLE = {"not UTF-8": (_not_utf8, "not UTF-8 text (byte"), "alias bomb": (_alias_bomb, "through its aliases"),
              "recursive alias": (_recursive_alias, "refers to its own anchor"), "deep": (_deep, "nested too deeply"),
              "250,000 values": (_many_values, "holds more than 200000 values (line 199"),
              "5000-digit integer": (_long_integer, "unreadable value")}


@pytest.mark.parametrize("module", ["daemon.commands.cli check-config", "daemon.commands.cli run"])
@pytest.mark.parametrize("bad", UNREADABLE)
def test_a_config_file_the_loader_cannot_take_exits_2_at_once(bad, module, tmp_path):
    """Non-UTF-8 bytes were a UnicodeDecodeError traceback, an alias bomb hung the loader (check-config too), deep
    nesting a RecursionError, a 5000-digit integer a ValueError: now one line each, exit 2, in well under a second
    of loading (a few seconds for 200,000 plain values, where the composing stops)."""
    make, expected = UNREADABLE[bad]
    config = make(tmp_path)
    cmd = [sys.executable, "-m", *module.split(), *(["--config"] if module.endswith("run") else []), str(config)]
    run = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert_config_error(run, expected)


def _run_briefly(argv: list[str], env: dict[str, str] | None = None,
                 timeout_s: float = 60) -> subprocess.CompletedProcess:
    """A command that must exit by itself: if it starts a daemon instead, its whole process group is killed."""
    proc = subprocess.Popen([sys.executable, "-m", "daemon.commands.cli", *argv], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            env=dict(os.environ, **(env or {})))
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        raise AssertionError(f"{argv[0]} did not exit by itself within {timeout_s} s: {err[-2000:]}") from None
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


def _runnable(tmp: Path, bus: dict | None = None, output_dir: str | None = None) -> Path:
    """sim.yaml with the files it names absolute (so every other check passes), a private bus, the given changes."""
    data = yaml.safe_load(SIM_CONFIG.read_text())
    data["sensors"]["can"]["dbc_file"] = str(ROOT / "configs" / "sim_car.dbc")
    data["sensors"]["lidar"]["metadata_file"] = str(ROOT / "configs" / "sim_os128_metadata.json")
    data["bus"] = {"shm_prefix": f"t{uuid.uuid4().hex[:12]}", **(bus or {})}
    data["recorder"]["output_dir"] = output_dir or str(tmp / "logs")
    path = tmp / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("case, bus, env, expected", [
    ("Lidar ring too small", {"ring_bytes": {"lidar/packets": 1000}}, {},
     "bus.ring_bytes['lidar/packets'] = 1000 cannot hold 2 of its 65535 B messages"),
    ("unknown topic", {"ring_bytes": {"lidar/pakets": 1 << 20}}, {},
     "bus.ring_bytes names unknown topics 'lidar/pakets'"),
    ("Docker's 64 MiB /dev/shm", {}, {"ROADLOG_SIMULATED_SHM_BYTES": str(64 << 20)},
     "rings need 455 MiB of /dev/shm, which holds 64 MiB"),
])
def test_rings_that_cannot_work_are_refused_by_check_config_and_by_the_daemon_before_it_starts(case, bus, env, expected,
                                                                                               tmp_path):
    """A ring smaller than its topic's messages (the driver died publishing), a ring for a topic that does not
    exist (a KeyError traceback in every process) and rings beyond /dev/shm (SIGBUS when the writer reached the
    60th MB, no message): check-config refuses them and `roadlog run` exits 2 before starting anything."""
    config = _runnable(tmp_path, bus=bus)
    assert_config_error(_run_briefly(["check-config", str(config), "--quiet"], env), expected)
    assert_config_error(_run_briefly(["run", "--config", str(config)], env), expected)
    assert not (tmp_path / "logs").exists()  # nothing started


def test_a_recorder_folder_that_cannot_be_made_is_refused_by_check_config_and_the_recorder(tmp_path):
    (tmp_path / "a_file").write_text("")
    config = _runnable(tmp_path, output_dir=str(tmp_path / "a_file" / "logs"))
    expected = "recorder.output_dir"
    assert_config_error(_run_briefly(["check-config", str(config), "--quiet"]), expected)
    run = subprocess.run([sys.executable, "-m", "daemon.processes.recorder", "--config", str(config)], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert_config_error(run, "is not a folder")
