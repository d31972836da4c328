"""The fits' torch device (`--device`, `mapper.device`): cpu runs through the real command, cuda without a GPU is a
configuration error everywhere it can be asked for (reconstruct, the live worker, check-config, the mapping bench),
and the optimisation loops of both fits copy no tensor between the host and the device (tests/mapping/
host_sync_watch.py: what would be a GPU round trip each step is caught on the CPU)."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

from daemon.spine.config import EXIT_CONFIG_ERROR
from daemon.spine.mapper_config import FaithfulFitConfig
from mapping.fits.reconstruction import reconstruct
from mapping.method.compute_device import optimisation_loop, resolve_device
from mapping.method.scene_data import StandingPoints
from mapping.offline.reconstruct_command import main as reconstruct_main
from tests.daemon_fixtures import REPO
from tests.mapping.host_sync_watch import HostSyncWatch
from tests.mapping.synthetic_road_scene import make_scene
from tests.mapping.test_mapping_reconstruction import CONFIG

SIM_CONFIG = REPO / "configs" / "sim.yaml"
no_gpu = pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA GPU is present: cuda is a valid device here")


def test_the_watch_catches_every_kind_of_round_trip_inside_a_loop_and_nothing_outside():
    t = torch.arange(6.0)
    host = np.arange(3)
    with HostSyncWatch() as watch:
        t.sum().item()  # outside every loop: not recorded
        with optimisation_loop("probe"):
            t.sum().item()
            float(t.max())
            t.tolist()
            t.numpy()
            np.asarray(t)
            t[host]
            t.to("cpu")
            torch.from_numpy(host)
            torch.tensor([1.0, 2.0])
            torch.zeros(3)
            torch.zeros(3, device=t.device)  # on the fit's device: fine
            t[1:3] * 2 + t.new_zeros(1)  # device work: fine
    whats = [what for _, what, _ in watch.found]
    assert whats == ["Tensor.item", "Tensor.__float__", "Tensor.tolist", "Tensor.numpy", "Tensor.__array__",
                     "__getitem__ with a host array index", "Tensor.to to a device", "torch.from_numpy",
                     "torch.tensor from host data", "torch.zeros without device="]
    assert {loop for loop, _, _ in watch.found} == {"probe"}
    assert all(where.startswith("tests/mapping/test_compute_device.py:") for _, _, where in watch.found)


@pytest.fixture(scope="module")
def scene():
    return make_scene(length_m=20.0, width=96, height=54, rate_hz=10.0)


@pytest.mark.parametrize(("faithful", "maskless"), [(False, False), (True, False), (False, True), (True, True)],
                         ids=["fast", "faithful", "fast-maskless", "faithful-maskless"])
def test_the_optimisation_loops_copy_nothing_between_host_and_device(scene, faithful, maskless):
    """Both fits on the synthetic road; `maskless`: every other view without semantics, tested against a wall the
    Lidar saw standing across the road (scans for the first 2 s only: the later views cannot be tested)."""
    config = CONFIG.model_copy(update={"device": "cpu", "faithful_fit": FaithfulFitConfig(epochs=1, batch_size=4)})
    keyframes, standing = scene.keyframes, None
    if maskless:
        keyframes = [dataclasses.replace(kf, semantics=None) if i % 2 else kf for i, kf in enumerate(keyframes)]
        wall = np.array([(12.0, y, z) for y in np.arange(-5, 5.01, 0.2) for z in np.arange(0.5, 2.51, 0.2)],
                        np.float32)
        standing = StandingPoints.of([(t, wall) for t in np.arange(0.0, 2.01, 0.1)])
    with HostSyncWatch() as watch:
        result = reconstruct(keyframes, scene.cameras, scene.trajectory, scene.lidar, config,
                             scene.reference_height_m, gt=scene.gt, faithful=faithful, holdout_every=5,
                             progress=False, lidar_standing=standing)
    assert watch.loops_seen == ({"faithful"} if faithful else {"fast elevation", "fast colour"})
    assert watch.found == []
    m = result.metrics
    assert m["steps"] > 1 and np.isfinite(m["loss_last"])
    if maskless:  # the test ran, inside the loop for the faithful fit
        assert m["maskless_hidden_pct"] > 1 and m["maskless_views_unchecked"] > 0
    assert result.road_map.colour_params.device.type == "cpu"  # the map comes back to the host after the fit


def test_reconstruct_on_the_cpu_device_through_the_command(city_drive, tmp_path, capsys):
    out = tmp_path / "map"
    with HostSyncWatch() as watch:
        code = reconstruct_main([str(city_drive), "--out", str(out), "--device", "cpu",
                                 "--gt", str(city_drive.with_name("city.gt.npz"))])
    assert code == 0
    assert watch.loops_seen == {"fast elevation", "fast colour"} and watch.found == []
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["path"] == "fast" and metrics["psnr_db"] > 20 and metrics["miou_pct"] > 40
    assert yaml.safe_load((out / "config.yaml").read_text())["mapper"]["device"] == "cpu"


def test_auto_is_the_cpu_without_a_gpu():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu").type == "cpu"


def _run(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *argv], cwd=REPO, capture_output=True, text=True, timeout=300)


def _one_error_line(run: subprocess.CompletedProcess, *words: str) -> None:
    assert run.returncode == EXIT_CONFIG_ERROR, run.stderr[-2000:]
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in run.stderr, run.stderr
    assert all(w in lines[0] for w in words), lines[0]


@no_gpu
def test_reconstruct_on_cuda_without_a_gpu_is_one_error_line(city_drive, tmp_path):
    run = _run("-m", "daemon.commands.cli", "reconstruct", str(city_drive), "--out", str(tmp_path / "map"),
               "--device", "cuda")
    _one_error_line(run, "--device", "cuda", "no CUDA GPU")
    assert not (tmp_path / "map").exists()


def _config_with_device(tmp_path, device: str):
    """configs/sim.yaml with mapper.device set, beside copies of the files it names."""
    for other in SIM_CONFIG.parent.iterdir():
        if other.is_file():
            shutil.copy(other, tmp_path / other.name)
    data = yaml.safe_load(SIM_CONFIG.read_text())
    data.setdefault("mapper", {})["device"] = device
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@no_gpu
def test_mapper_device_cuda_without_a_gpu_is_refused_by_check_config_the_worker_and_reconstruct(city_drive,
                                                                                              tmp_path):
    config = _config_with_device(tmp_path, "cuda")
    _one_error_line(_run("-m", "daemon.commands.cli", "check-config", str(config)), "mapper.device", "cuda")
    _one_error_line(_run("-m", "mapping.live.mapping_worker", "--config", str(config), "--output-dir",
                         str(tmp_path / "out")), "mapper.device", "no CUDA GPU")
    _one_error_line(_run("-m", "daemon.commands.cli", "reconstruct", str(city_drive), "--out", str(tmp_path / "m"),
                         "--config", str(config)), "mapper.device", "no CUDA GPU")
    plain = _config_with_device(tmp_path, "auto")  # the worker's own --device cuda too
    _one_error_line(_run("-m", "mapping.live.mapping_worker", "--config", str(plain), "--output-dir",
                         str(tmp_path / "out"), "--device", "cuda"), "mapper.device", "no CUDA GPU")


def test_an_unknown_device_is_a_config_error_naming_the_key(tmp_path):
    run = _run("-m", "daemon.commands.cli", "check-config", str(_config_with_device(tmp_path, "gpu")))
    assert run.returncode == EXIT_CONFIG_ERROR and "mapper.device" in run.stderr and "Traceback" not in run.stderr


@no_gpu
def test_the_mapping_bench_on_cuda_without_a_gpu_says_so_and_exits_2():
    _one_error_line(_run("bench/mapping.py", "--device", "cuda"), "--device", "no CUDA GPU")
