"""The `roadlog` command as a user meets it, through real subprocesses of its entry point: a bad path or input is
one `error:` line on stderr and exit status 2 (never a traceback), `--version`, and where `replay` writes."""

import os
import socket
import subprocess

import pytest

from daemon.bus.pubsub import unlink_all
from tests.daemon_fixtures import private_config
from tests.roadlog_cli import can_only_log, roadlog


def assert_one_line_error(run: subprocess.CompletedProcess, *words: str) -> None:
    assert run.returncode == 2, (run.returncode, run.stderr[-2000:])
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in run.stderr, run.stderr[-2000:]
    for word in words:
        assert word in lines[0], (word, lines[0])


def test_version():
    run = roadlog("--version")
    assert run.returncode == 0 and run.stdout.strip().startswith("roadlog 0.") and not run.stderr


@pytest.fixture
def files(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(os.urandom(4096))
    bad_yaml, control = tmp_path / "bad.yaml", tmp_path / "control.yaml"
    bad_yaml.write_text("vehicle:\n  frame: [base\n")  # the flow sequence never closed
    control.write_text("vehicle: \x07\n")  # a control character: the YAML reader refuses it
    car, config = private_config(tmp_path)
    log = can_only_log(tmp_path / "drive.mcap", car)
    return {"missing": tmp_path / "nope.mcap", "junk": junk, "folder": tmp_path, "config": config, "log": log,
            "missing_config": tmp_path / "nope.yaml", "junk_config": junk, "bad_yaml": bad_yaml, "control": control}


@pytest.mark.parametrize(("args", "words"), [
    (("log-info", "{missing}"), ("nope.mcap", "no such file")),
    (("log-info", "{junk}"), ("is not an MCAP file",)),
    (("log-info", "{folder}"), ("a folder",)),
    (("reconstruct", "{missing}", "--out", "{folder}/map"), ("nope.mcap",)),
    (("reconstruct", "{junk}", "--out", "{folder}/map"), ("is not an MCAP file",)),
    (("reconstruct", "{junk}", "--out", "{folder}/map", "--config", "{missing_config}"), ("nope.yaml",)),
    (("reconstruct", "{log}", "--out", "{folder}/map", "--gt", "{missing}"), ("--gt", "nope.mcap")),
    (("reconstruct", "{log}", "--out", "{folder}/map", "--gt", "{junk}"), ("--gt", "ground truth")),
    (("reconstruct", "{log}", "--out", "{junk}"), ("--out", "not a folder")),
    (("reconstruct", "{log}", "--out", "{folder}/map", "--faithful", "--epochs", "0"), ("--epochs 0", ">= 1")),
    (("status-server", "--config", "{missing_config}"), ("nope.yaml",)),
    (("status-server", "--config", "{junk_config}"), ("junk.mcap",)),
    (("status-server", "--config", "{config}", "--port", "99999"), (":99999", "port must be 0-65535")),
    (("check-config", "{missing_config}"), ("nope.yaml",)),
    (("check-config", "{bad_yaml}"), ("bad.yaml: not valid YAML: line 3, column 1: expected ',' or ']'",
                                      "while parsing a flow sequence from line 2, column 10")),
    (("check-config", "{control}"), ("control.yaml: not valid YAML: position 9: unacceptable character #x0007",)),
    (("reconstruct", "{log}", "--out", "{folder}/map", "--config", "{bad_yaml}"), ("bad.yaml", "line 3, column 1")),
    (("simulate", "--scenario", "city", "--out", "{folder}/no/such/folder/x.mcap"), ("no folder",)),
    (("simulate", "--scenario", "city", "--out", "{folder}"), ("a folder",)),
    (("simulate", "--scenario", "nowhere", "--out", "{folder}/x.mcap"), ("unknown scenario 'nowhere'",)),
    (("simulate", "--scenario", "random", "--seed", "-1", "--out", "{folder}/x.mcap"), ("--seed -1",)),
    (("simulate", "--scenario", "city", "--seconds", "0", "--out", "{folder}/x.mcap"), ("--seconds 0",)),
    (("simulate", "--scenario", "city", "--seconds", "100", "--out", "{folder}/x.mcap"),
     ("--seconds 100", "scenario city", "at most")),
    (("simulate", "--scenario", "city", "--seconds", "inf", "--out", "{folder}/x.mcap"), ("--seconds inf",)),
    (("simulate", "--scenario", "city", "--config", "{missing_config}", "--out", "{folder}/x.mcap"), ("nope.yaml",)),
    (("replay", "{missing}", "--config", "{config}"), ("nope.mcap", "no such file")),
    (("replay", "{folder}", "--config", "{config}"), ("a folder",)),
    (("replay", "{junk}", "--config", "{config}"), ("is not an MCAP file",)),
    (("replay", "{log}", "--config", "{config}", "--rate", "fast", "--output-dir", "{folder}/out"), ("--rate fast",)),
    (("replay", "{log}", "--config", "{config}", "--rate", "0", "--output-dir", "{folder}/out"), ("--rate 0",)),
    (("replay", "{log}", "--config", "{config}", "--rate", "nan", "--output-dir", "{folder}/out"), ("--rate nan",)),
    (("run", "--config", "{missing_config}"), ("nope.yaml",)),
    (("demo", "--scenario", "nowhere", "--out", "{folder}/demo"), ("unknown scenario 'nowhere'",)),
    (("demo", "--seconds", "0", "--out", "{folder}/demo"), ("--seconds 0",)),
    (("import", "kitti-raw", "{missing}", "--out", "{folder}/x.mcap"), ("nope.mcap",)),
])
def test_a_bad_path_or_input_is_one_error_line_and_exit_2(files, args, words):
    """Refused before any work: a replay before it starts any process (their lines would follow), a simulation
    before it renders the drive."""
    assert_one_line_error(roadlog(*(a.format(**files) for a in args), timeout=120), *words)


def test_a_status_port_in_use_is_one_error_line_not_a_traceback(tmp_path):
    """The status server alone, and so the daemon's (exit 2: the supervisor does not restart it in a loop)."""
    _, config = private_config(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert_one_line_error(roadlog("status-server", "--config", config, "--port", port), f":{port}", "in use")


def test_replay_writes_under_roadlog_output_in_the_current_folder_never_beside_the_config(tmp_path):
    """Without --output-dir a replay's recording and map go to ./roadlog-output, not to recorder.output_dir (which
    sits beside the config: configs/logs for configs/sim.yaml). A drive the mapper gets no odometry from (no wheel
    speeds) ends without a map window, not with an IndexError."""
    (tmp_path / "configs").mkdir()
    config, path = private_config(tmp_path / "configs", status={"port": 0})
    log = can_only_log(tmp_path / "drive.mcap", config)
    work = tmp_path / "work"
    work.mkdir()
    try:
        run = roadlog("replay", log, "--config", path, "--rate", "max", cwd=work, timeout=300)
    finally:
        unlink_all(config)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "Traceback" not in run.stderr and "IndexError" not in run.stderr, run.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "configs").iterdir()) == ["car.yaml"]
    out = work / "roadlog-output"
    assert len(list(out.glob("roadlog_*.mcap"))) == 1 and (out / "map").is_dir()
