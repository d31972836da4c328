"""Pose refinement (mapping.fits.pose_refinement): a known pose error in part of a drive is found and corrected
by the fast fit; off, the fit is what it was; the injected noise of the benches (mapping.localization.pose_noise)
has the RMS asked for."""

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from daemon.spine.config import ConfigError, config_to_yaml, load_config, parse_config
from daemon.spine.mapper_config import InputsConfig, MapperConfig, MeshConfig, WindowsConfig
from mapping.fits.reconstruction import lidar_refinement_unavailable, reconstruct
from mapping.localization.pose_noise import PoseNoise, perturbed, residual_error
from mapping.localization.trajectory import Trajectory
from mapping.offline.reconstruct_command import config_from_logs, with_pose_refinement
from tests.mapping.synthetic_road_scene import make_scene

REPO = Path(__file__).resolve().parents[2]

CONFIG = MapperConfig(mesh=MeshConfig(side_m=0.1, corridor_half_width_m=5.0),
                      inputs=InputsConfig(keyframe_spacing_m=0.0), windows=WindowsConfig(before_m=20.0, after_m=20.0))
SHIFT_M = np.array([0.0, 0.15, 0.0])  # 15 cm to the left, the keyframes between 8 and 14 m
SHIFTED_S = (8.0, 14.0)


@pytest.fixture(scope="module")
def scene():
    return make_scene(length_m=22.0, width=128, height=72, rate_hz=10.0)


def _shifted(scene):
    """The scene's keyframes, those in SHIFTED_S moved by SHIFT_M (a pose error there): their images are what the
    true poses saw."""
    s = scene.trajectory.horizontal_distance_at(np.array([kf.timestamp for kf in scene.keyframes]))
    out = []
    for kf, si in zip(scene.keyframes, s, strict=True):
        T = kf.T_world_camera.copy()
        if SHIFTED_S[0] <= si <= SHIFTED_S[1]:
            T[:3, 3] += SHIFT_M
        out.append(replace(kf, T_world_camera=T))
    return out


def _run(scene, keyframes, enabled: bool):
    refinement = CONFIG.pose_refinement.model_copy(update={"enabled": enabled, "knot_spacing_m": 1.0})
    config = CONFIG.model_copy(update={"pose_refinement": refinement})
    return reconstruct(keyframes, scene.cameras, scene.trajectory, scene.lidar, config, scene.reference_height_m,
                       gt=scene.gt, holdout_every=5, progress=False)


@pytest.fixture(scope="module")
def runs(scene):
    keyframes = _shifted(scene)
    return _run(scene, scene.keyframes, False), _run(scene, keyframes, False), _run(scene, keyframes, True)


@pytest.mark.slow
@pytest.mark.timeout(1800)  # three reconstructions: ~11 min on the shared 2 cores under load
def test_a_known_pose_error_is_found_and_the_map_recovers(runs):
    exact, shifted, refined = runs
    corrections = refined.pose_corrections
    position, _ = corrections.at(np.array([10.0, 11.0, 12.0]))  # inside the shifted part
    assert np.abs(position[:, 1] + SHIFT_M[1]).max() < 0.05  # 15 cm found to within 5 cm
    before, _ = corrections.at(np.array([2.0, 3.0, 5.0]))
    assert np.abs(before).max() < 0.04  # the drive before it keeps its poses (the track's far end, seen by fewer
    # views and by those of the shifted part, is pulled ~7 cm along)
    assert shifted.metrics["psnr_db"] < exact.metrics["psnr_db"] - 0.5  # the error costs the map ...
    assert refined.metrics["psnr_db"] > shifted.metrics["psnr_db"] + 0.5  # ... and the refinement wins most back
    assert refined.metrics["pose_refinement"]["knots"] == len(corrections.knots_s)
    assert refined.metrics["pose_refinement_wall_s"] > 0


@pytest.mark.slow
@pytest.mark.timeout(1800)  # three reconstructions: ~11 min on the shared 2 cores under load
def test_without_refinement_there_are_no_corrections_and_no_figures(runs):
    exact, shifted, _ = runs
    for run in (exact, shifted):
        assert run.pose_corrections is None
        assert "pose_refinement" not in run.metrics and "pose_refinement_wall_s" not in run.metrics


def test_injected_pose_noise_has_the_rms_asked_and_a_correction_of_its_opposite_leaves_none():
    times = np.arange(0, 10_000_000_000, 10_000_000, dtype=np.int64)
    positions = np.stack([np.linspace(0, 80, len(times)), np.zeros(len(times)), np.zeros(len(times))], 1)
    exact = Trajectory(times, positions, np.tile([0, 0, 0, 1.0], (len(times), 1)), 50.0, 8.0, 100.0)
    noise = PoseNoise(0.15, 0.2, 0.5, seed=4)
    noisy = perturbed(exact, noise)
    error = np.linalg.norm(noisy.positions - exact.positions, axis=1)
    assert np.sqrt((error ** 2).mean()) == pytest.approx(0.15, rel=1e-6)
    seconds = (times - times[0]) / 1e9
    before = residual_error(noise, noisy, seconds)
    assert before["position_rms_cm"] == pytest.approx(15.0, rel=1e-6)
    assert before["rotation_rms_deg"] == pytest.approx(0.2 * np.sqrt(3), rel=1e-3)
    position, rotation = noise.error_at(noisy, seconds)
    # per component in the track's frame: this track runs along x (east), so along is x, across y (to 1 %: the
    # heading is the perturbed trajectory's, 0.2 degrees off)
    assert before["along_rms_cm"] == pytest.approx(100 * np.sqrt((position[:, 0] ** 2).mean()), rel=1e-2)
    assert before["across_rms_cm"] == pytest.approx(100 * np.sqrt((position[:, 1] ** 2).mean()), rel=1e-2)
    assert before["yaw_rms_deg"] == pytest.approx(np.rad2deg(np.sqrt((rotation[:, 2] ** 2).mean())), rel=1e-3)
    assert before["along_rms_cm"] ** 2 + before["across_rms_cm"] ** 2 + before["vertical_rms_cm"] ** 2 \
        == pytest.approx(before["position_rms_cm"] ** 2, rel=1e-6)
    mean = position[:, :2].mean(0)
    assert before["common_horizontal_cm"] == pytest.approx(100 * np.hypot(*mean), rel=1e-6)
    assert before["common_along_cm"] == pytest.approx(100 * mean[0], rel=1e-2)  # the track runs along x
    assert before["common_across_cm"] == pytest.approx(100 * mean[1], rel=1e-2, abs=0.01)
    assert before["relative_horizontal_rms_cm"] ** 2 + before["common_horizontal_cm"] ** 2 \
        == pytest.approx(before["horizontal_rms_cm"] ** 2, rel=1e-6)
    shifted = residual_error(noise, noisy, seconds, np.tile([0.0, 0.0, 0.0], (len(seconds), 1)) - [*mean, 0.0],
                             np.zeros((len(seconds), 3)))
    assert shifted["common_horizontal_cm"] < 1e-9  # a common shift moves only the common part
    places = exact.interpolate(times[0] + np.rint(seconds * 1e9).astype(np.int64))[0][:, :2]
    turn = 0.002  # rad, about the places' centroid: a position error of a (-qy, qx)
    q = places - places.mean(0)
    turned = residual_error(noise, noisy, seconds, -position + np.c_[-turn * q[:, 1], turn * q[:, 0], 0 * q[:, 0]],
                            -rotation)
    assert turned["rigid_turn_deg"] == pytest.approx(np.rad2deg(turn), rel=1e-2)  # (the perturbed trajectory's
    assert turned["nonrigid_horizontal_rms_cm"] < 0.05  # places are within 20 cm of the exact ones)
    assert shifted["relative_horizontal_rms_cm"] == pytest.approx(before["relative_horizontal_rms_cm"], rel=1e-9)
    after = residual_error(noise, noisy, seconds, -position, -rotation)
    assert after["position_rms_cm"] < 1e-9 and after["rotation_rms_deg"] < 1e-9
    assert max(after[k] for k in ("along_rms_cm", "across_rms_cm", "vertical_rms_cm", "yaw_rms_deg")) < 1e-9
    assert PoseNoise(0.15, 0.2, 0.5, seed=5).error_at(noisy, seconds)[0][0, 0] != position[0, 0]


def _reconstruct(*args):
    return subprocess.run([sys.executable, "-m", "daemon.commands.cli", "reconstruct", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=1500)


def test_bad_pose_noise_is_one_error_line_and_exit_2(tmp_path):
    done = _reconstruct(tmp_path / "drive.mcap", "--out", tmp_path / "map", "--pose-noise-m", "-0.1")
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == ["error: --pose-noise-m and --pose-noise-deg must be >= 0, "
                                                "--pose-noise-every-s > 0"]


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_reconstruct_with_injected_noise_reports_the_error_the_refinement_leaves(city_drive, tmp_path):
    noise = ("--pose-noise-m", "0.2", "--pose-noise-deg", "0.05", "--gt", city_drive.with_suffix(".gt.npz"))
    done = _reconstruct(city_drive, "--out", tmp_path / "refined", *noise, "--pose-refinement", "on")
    assert done.returncode == 0, done.stderr[-2000:]
    m = json.loads((tmp_path / "refined" / "metrics.json").read_text())
    before, after = m["pose_noise"]["keyframes_before"], m["pose_noise"]["keyframes_after"]
    assert 15.0 < before["position_rms_cm"] < 25.0  # the RMS over the trajectory's poses is 20 cm
    assert after["position_rms_cm"] < 0.9 * before["position_rms_cm"]
    assert m["pose_refinement"]["knots"] > 2 and m["pose_refinement_wall_s"] > 0

    def vertical(error: dict) -> float:
        return float(np.sqrt(max(error["position_rms_cm"] ** 2 - error["horizontal_rms_cm"] ** 2, 0.0)))

    registration = m["lidar_registration"]  # the drive has Lidar: its ground registered the height first
    assert registration["points"] > 10_000 and registration["points_skipped"] == 0
    assert registration["knots"] == m["pose_refinement"]["knots"] and m["lidar_registration_wall_s"] > 0
    assert vertical(after) < 0.5 * vertical(before)


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_reconstruct_with_the_lidar_registration_of_every_axis_takes_the_horizontal_error_out(city_drive, tmp_path):
    """`--pose-refinement lidar`: the Lidar ground's heights and intensity give every axis (mapping.fits
    .lidar_horizontal_registration), the drive is read again with the corrected trajectory."""
    noise = ("--pose-noise-m", "0.2", "--pose-noise-deg", "0.05", "--gt", city_drive.with_suffix(".gt.npz"))
    done = _reconstruct(city_drive, "--out", tmp_path / "lidar", *noise, "--pose-refinement", "lidar")
    assert done.returncode == 0, done.stderr[-2000:]
    m = json.loads((tmp_path / "lidar" / "metrics.json").read_text())
    before, after = m["pose_noise"]["keyframes_before"], m["pose_noise"]["keyframes_after"]
    assert 15.0 < before["position_rms_cm"] < 25.0
    assert after["along_rms_cm"] < 0.5 * before["along_rms_cm"]
    assert after["across_rms_cm"] < 0.5 * before["across_rms_cm"]
    assert after["vertical_rms_cm"] < 0.5 * before["vertical_rms_cm"]
    horizontal = m["lidar_horizontal_registration"]
    assert horizontal["points_with_contrast"] == horizontal["points"] > 10_000  # the simulated Ouster's signal
    assert m["lidar_pre_pass_wall_s"] > 0 and m["pose_refinement"]["knots"] == horizontal["knots"]


def test_the_refinement_switch_sets_the_photometric_only_path():
    car = load_config(REPO / "configs" / "sim.yaml")
    settings = {name: with_pose_refinement(car, name).mapper.pose_refinement
                for name in ("on", "off", "photometric", "lidar")}
    assert settings["on"].enabled and settings["on"].lidar_registration and not settings["on"].lidar_horizontal
    assert settings["lidar"].enabled and settings["lidar"].lidar_registration and settings["lidar"].lidar_horizontal
    assert settings["photometric"].enabled and not settings["photometric"].lidar_registration
    assert not settings["off"].enabled
    assert with_pose_refinement(car, None) is car


def test_lidar_refinement_says_why_it_could_not_run():
    lidar = with_pose_refinement(load_config(REPO / "configs" / "sim.yaml"), "lidar").mapper.pose_refinement
    assert lidar_refinement_unavailable(lidar, True, True, True) is None  # it ran
    assert "no Lidar ground points" in lidar_refinement_unavailable(lidar, True, False, False)
    assert "without Lidar supervision" in lidar_refinement_unavailable(lidar, False, True, True)
    assert "firing times" in lidar_refinement_unavailable(lidar, True, True, False)
    for setting in ("on", "off", "photometric"):  # not asked for: nothing to say
        refine = with_pose_refinement(load_config(REPO / "configs" / "sim.yaml"), setting).mapper.pose_refinement
        assert lidar_refinement_unavailable(refine, True, False, False) is None


def test_the_horizontal_registration_without_the_height_one_is_a_config_error():
    import yaml

    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    data["mapper"]["pose_refinement"] = {"enabled": True, "lidar_horizontal": True, "lidar_registration": False}
    with pytest.raises(ConfigError, match="pose_refinement.*lidar_horizontal needs lidar_registration"):
        parse_config(data)


def test_lidar_refinement_on_a_drive_without_lidar_warns_and_reports_the_photometric_fit(city_drive, tmp_path):
    """`--pose-refinement lidar` with no Lidar ground (here `--no-lidar`): the photometric refinement runs instead,
    said on stderr and in metrics `pose_refinement` (not silently). (A short photometric fit: one round of a few
    steps, what is checked is which fit ran.)"""
    config, config_path = config_from_logs([str(city_drive)])
    refine = config.mapper.pose_refinement.model_copy(update={"steps": 3, "blur_px": (2.0,)})
    short = config_path.with_name("short_refinement.yaml")  # beside the recorded Lidar metadata it names
    short.write_text(config_to_yaml(config.model_copy(update={"mapper": config.mapper.model_copy(
        update={"pose_refinement": refine})})))
    done = _reconstruct(city_drive, "--out", tmp_path / "map", "--config", short, "--no-lidar",
                        "--pose-refinement", "lidar")
    assert done.returncode == 0, done.stderr[-2000:]
    warnings = [line for line in done.stderr.splitlines() if "--pose-refinement lidar" in line]
    assert warnings == ["roadlog reconstruct: warning: --pose-refinement lidar (mapper.pose_refinement."
                        "lidar_horizontal) asked for, but no Lidar ground points (a drive without Lidar, or "
                        "--no-lidar): the photometric refinement instead"]
    m = json.loads((tmp_path / "map" / "metrics.json").read_text())
    assert m["pose_refinement"]["source"] == "photometric"
    assert m["pose_refinement"]["lidar_unavailable"].startswith("no Lidar ground points")
    assert "lidar_horizontal_registration" not in m and "lidar_pre_pass_wall_s" not in m
