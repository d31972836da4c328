"""Each camera's orientation checked against the poses by its images (mapping.localization.camera_orientation), on
the simulated city drive: its cameras were rendered with sim.yaml's extrinsics, and a config that turns one camera's
mount is what a car with a bad calibration hands the mapper."""

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from daemon.spine.config import load_config, parse_config
from daemon.spine.mapper_config import CameraCheckConfig
from mapping.inputs.drive_inputs import load_drive
from mapping.localization.camera_orientation import check_orientations, corrected_keyframes, significant
from tests.daemon_fixtures import REPO

TURNS = {"front_wide": (0, 0, 2.0), "front_left": (0, -1.5, 0)}  # roll, pitch, yaw added to the true mount (deg)


def turned_config_data() -> dict:
    """sim.yaml with TURNS added to two cameras' extrinsics, its input files named absolutely."""
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["sensors"]["can"]["dbc_file"] = str(REPO / "configs" / data["sensors"]["can"]["dbc_file"])
    data["sensors"]["lidar"]["metadata_file"] = str(REPO / "configs" / data["sensors"]["lidar"]["metadata_file"])
    for camera in data["sensors"]["cameras"]:
        if camera["name"] in TURNS:
            true = Rotation.from_euler("xyz", camera["extrinsics"]["rotation_rpy_deg"], degrees=True)
            turn = Rotation.from_euler("xyz", TURNS[camera["name"]], degrees=True)  # about the vehicle's axes
            camera["extrinsics"]["rotation_rpy_deg"] = (turn * true).as_euler("xyz", degrees=True).tolist()
    return data


@pytest.fixture(scope="module")
def drives(city_drive):
    """The city drive's keyframes placed with the true extrinsics and with the turned ones."""
    true = load_config(REPO / "configs" / "sim.yaml")
    turned = parse_config(turned_config_data())
    return (load_drive([city_drive], true, REPO / "configs" / "sim.yaml", use_lidar=False),
            load_drive([city_drive], turned, REPO / "configs" / "sim.yaml", use_lidar=False))


def test_the_check_reads_the_true_mounts_as_right(drives):
    true, _ = drives
    checks = check_orientations(true.keyframes, true.cameras, CameraCheckConfig(mode="report"))
    for name, check in checks.items():
        assert check is not None and check.pairs_used >= 12, name
        # the forward camera sees the direction of travel in its image; the side cameras, 45 degrees off it, less well
        bound = 0.25 if name == "front_wide" else 0.6
        assert abs(check.yaw_deg) < bound and abs(check.pitch_deg) < bound, (name, check.summary())
        assert max(check.std_deg) < bound / 2, (name, check.summary())


def test_the_check_finds_each_turned_mount_and_its_correction_restores_the_true_orientation(drives):
    true, turned = drives
    checks = check_orientations(turned.keyframes, turned.cameras, CameraCheckConfig(mode="apply"))
    for name, check in checks.items():
        _, pitch, yaw = TURNS.get(name, (0, 0, 0))
        bound = 0.25 if name == "front_wide" else 0.6
        assert check.yaw_deg == pytest.approx(-yaw, abs=bound), (name, check.summary())  # the turn back
        assert check.pitch_deg == pytest.approx(-pitch, abs=bound), (name, check.summary())
    assert checks["front_wide"].median_angle_before_deg > 1.5 > 0.5 > checks["front_wide"].median_angle_after_deg
    corrected = corrected_keyframes(turned.keyframes, checks, CameraCheckConfig(mode="apply"))
    corrected = {(k.camera, k.timestamp): k for k in corrected}
    placed = {(k.camera, k.timestamp): k for k in turned.keyframes}
    for k in true.keyframes:  # each turned camera's keyframes nearer their true orientation, in the same place
        key = (k.camera, k.timestamp)
        before, after = (np.degrees(Rotation.from_matrix(k.T_world_camera[:3, :3].T @ kf[key].T_world_camera[:3, :3])
                                    .magnitude()) for kf in (placed, corrected))
        if k.camera == "front_wide":  # its check is significant: corrected
            assert before == pytest.approx(2.0, abs=0.01) and after < 0.25, (before, after)
        elif k.camera == "front_left" and significant(checks[k.camera], CameraCheckConfig()):
            assert before == pytest.approx(1.5, abs=0.01) and after < 0.6, (before, after)
        else:  # a reading within the check's noise leaves a camera as it was
            assert after == before, (k.camera, before, after)
        assert np.allclose(k.T_world_camera[:3, 3], corrected[key].T_world_camera[:3, 3])


def test_reconstruct_reports_and_applies_the_check(city_drive, tmp_path):
    """(The map after the check is made short: no photometric elevation, a few colour steps; what is checked is the
    check's report and its corrections, the map's quality is not.)"""
    data = turned_config_data()
    data["mapper"]["fast_fit"].update(photometric_elevation=False, colour_encoder_steps=10)
    config = tmp_path / "turned.yaml"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "map"
    run = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "reconstruct", str(city_drive),
                          "--out", str(out), "--config", str(config), "--no-lidar", "--camera-check", "apply"],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    check = json.loads((out / "metrics.json").read_text())["camera_check"]
    assert check["mode"] == "apply" and set(check["cameras"]) == {"front_wide", "front_left", "front_right"}
    wide, left = (check["cameras"][n] for n in ("front_wide", "front_left"))
    assert wide["yaw_deg"] == pytest.approx(-2.0, abs=0.25) and wide["warned"]
    assert left["pitch_deg"] == pytest.approx(1.5, abs=0.6)
    warned = [line for line in run.stderr.splitlines() if "from where its extrinsics and the poses place it" in line]
    assert len(warned) == sum(c["warned"] for c in check["cameras"].values()) >= 1, warned
    assert all(line.endswith(": corrected") for line in warned) and "front_wide" in warned[0], warned
    assert "camera orientations checked against the poses and corrected" in run.stderr
