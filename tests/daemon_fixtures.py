"""Shared set-up for daemon tests: a sim config with a private bus prefix, written to a file."""

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
