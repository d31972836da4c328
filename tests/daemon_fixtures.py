"""Shared set-up for daemon tests: a sim config with a private bus prefix, written to a file; free ports; the status
endpoint asked over HTTP; waiting for a condition."""

import json
import socket
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import yaml

from daemon.spine.config import CarConfig, load_config

REPO = Path(__file__).resolve().parents[1]


def private_config(tmp_path: Path, *, point_clouds: bool = False, **updates) -> tuple[CarConfig, Path]:
    """configs/sim.yaml with a unique shm prefix (and any section updates), saved in tmp_path; `point_clouds`: its
    Lidar one whose scans come decoded (model point-cloud, no metadata file)."""
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["bus"] = {"shm_prefix": f"t{uuid.uuid4().hex[:10]}"}
    for section, values in updates.items():
        data.setdefault(section, {}).update(values)
    if point_clouds:
        data["sensors"]["lidar"]["model"] = "point-cloud"
        del data["sensors"]["lidar"]["metadata_file"]
    else:
        data["sensors"]["lidar"]["metadata_file"] = str(REPO / "configs" / data["sensors"]["lidar"]["metadata_file"])
    data["sensors"]["can"]["dbc_file"] = str(REPO / "configs" / data["sensors"]["can"]["dbc_file"])
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path), path


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port of 127.0.0.1 free now (TCP, or UDP with kind=socket.SOCK_DGRAM)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def http_get(port: int, path: str, timeout_s: float = 3.0) -> tuple[int | None, bytes]:
    """GET http://127.0.0.1:PORT/PATH: the answer's status and body, (None, b"") when nothing answers."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=timeout_s) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()
    except OSError:
        return None, b""


def http_json(port: int, path: str, timeout_s: float = 3.0) -> tuple[int | None, dict]:
    """As http_get, the body read as a JSON object ({} for any other body)."""
    code, body = http_get(port, path, timeout_s)
    try:
        doc = json.loads(body) if body.startswith(b"{") else {}
    except ValueError:
        doc = {}
    return code, doc


def wait_for(predicate, timeout_s: float, what: str, poll_s: float = 0.1):
    """The first true value of predicate(), polled until timeout_s (then an AssertionError naming `what`)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise AssertionError(f"timed out waiting for {what}")
