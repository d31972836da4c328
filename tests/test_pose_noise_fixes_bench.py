"""bench/pose_noise_fixes.py (bench/pose_noise.py --noise-at fixes): the GNSS error model has the sigma, time
constant and white share asked for, and a perturbed log carries exactly that error in its fixes (what the pose
fusion reads), with the sigma in their covariance, every other message as it was."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from daemon.log_format.reader import read_log
from daemon.log_format.writer import LogWriter
from daemon.spine.local_frame import LocalFrame
from daemon.spine.messages import GnssFix, ImuSample
from daemon.spine.topics import GNSS_FIX, IMU
from tests.daemon.test_log_format import CONFIG

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fixes_bench():
    spec = importlib.util.spec_from_file_location("pose_noise_fixes", REPO / "bench" / "pose_noise_fixes.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up
    spec.loader.exec_module(module)
    return module


def _lag_correlation(x: np.ndarray, lag: int) -> float:
    return float(np.corrcoef(x[:-lag], x[lag:])[0, 1])


def test_gauss_markov_sigma_and_time_constant(fixes_bench):
    t = np.arange(0.0, 4000.0, 0.1)  # 400 time constants
    x = fixes_bench.gauss_markov(t, 0.1, 10.0, np.random.default_rng(3))
    assert abs(x.std() - 0.1) < 0.012
    assert abs(_lag_correlation(x, 100) - np.exp(-1.0)) < 0.08  # at one time constant
    assert _lag_correlation(x, 1) > 0.98


def test_fix_errors_rms_split_and_white_share(fixes_bench):
    noise = fixes_bench.FixNoise(position_rms_m=0.2, tau_s=10.0, white_fraction=0.2, vertical_ratio=1.5, seed=4)
    t = np.arange(0.0, 4000.0, 0.1)
    error = fixes_bench.fix_errors(t, noise)
    assert np.sqrt((error ** 2).sum(1).mean()) == pytest.approx(0.2, rel=1e-9)  # scaled to the RMS asked for
    h, v = noise.sigmas_m()
    assert 2 * h * h + v * v == pytest.approx(0.04)
    assert error[:, 2].std() / error[:, :2].std() == pytest.approx(1.5, rel=0.15)
    # the white share: from one epoch to the next only the Gauss-Markov part (80 % of the variance) carries over
    assert _lag_correlation(error[:, 0], 1) == pytest.approx(0.8 * np.exp(-0.01), abs=0.03)
    short = fixes_bench.fix_errors(np.arange(0.0, 6.0, 0.1), noise)  # a 6 s drive: still the RMS asked for
    assert np.sqrt((short ** 2).sum(1).mean()) == pytest.approx(0.2, rel=1e-9)


def test_perturbed_log_moves_only_the_fixes(fixes_bench, tmp_path):
    frame = LocalFrame(48.1, 11.5, 520.0)
    src, dst = tmp_path / "exact.mcap", tmp_path / "perturbed.mcap"
    enu = np.stack([np.arange(30) * 1.0, np.arange(30) * 0.5, np.zeros(30)], 1)
    lat, lon, alt = frame.enu_to_geodetic(enu)
    cov = (0.0002, 0, 0, 0, 0.0002, 0, 0, 0, 0.0004)
    with LogWriter(src, CONFIG) as writer:
        for i in range(30):
            t = 1_000_000_000 + i * 100_000_000
            writer.write(GNSS_FIX, GnssFix(i, t, t, float(lat[i]), float(lon[i]), float(alt[i]), cov, 2))
            writer.write(IMU, ImuSample(i, t, t, (0.1 * i, 0.0, 9.8), (0.0, 0.0, 0.01)))
    noise = fixes_bench.FixNoise(position_rms_m=0.15, tau_s=5.0, seed=1)
    drawn = fixes_bench.perturb_log(src, dst, noise)
    assert drawn["fixes"] == 30 and drawn["error_rms_cm"] == pytest.approx(15.0)
    read = {topic: [r.message for r in read_log([dst]) if r.topic == topic] for topic in (GNSS_FIX, IMU)}
    fixes = read[GNSS_FIX]
    assert len(fixes) == 30
    moved = frame.geodetic_to_enu(np.array([f.latitude_deg for f in fixes]), np.array([f.longitude_deg for f in fixes]),
                                  np.array([f.altitude_m for f in fixes])) - enu
    expected = fixes_bench.fix_errors(np.arange(30) * 0.1, noise)
    assert np.abs(moved - expected).max() < 1e-3  # the error drawn, in every fix
    assert np.sqrt((moved ** 2).sum(1).mean()) == pytest.approx(0.15, abs=1e-3)
    h, v = noise.sigmas_m()
    assert np.allclose(np.reshape(fixes[0].position_covariance, (3, 3)), np.diag([h * h, h * h, v * v]))
    original = [r.message for r in read_log([src]) if r.topic == IMU]
    assert [(m.sensor_time_ns, m.accel_mps2) for m in read[IMU]] == [(m.sensor_time_ns, m.accel_mps2)
                                                                      for m in original]


def test_registered_miou_finds_a_maps_shift(fixes_bench, tmp_path):
    """A map whose markings lie 6 cm east and 4 cm south of the truth's scores lower as placed; registered, fleet's
    shift moves it back (the score then polishes it within 3 cm: on a 10 cm raster it is flat within a few cm) and
    it scores as a map in place."""
    t_res, size = 0.05, 20.0

    def classes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        cls = np.zeros(x.shape, np.uint8)  # road
        cls[(np.mod(x, 1.7) < 0.15)] = 1  # lane markings across x, 15 cm wide
        cls[(np.mod(y, 2.3) < 0.15) & (np.mod(x, 3.0) < 1.5)] = 1  # dashes across y
        cls[np.hypot(np.mod(x, 4.1) - 2.0, np.mod(y, 3.7) - 1.8) < 0.3] = 3  # manholes
        return cls

    n = int(size / t_res)
    jj, ii = np.meshgrid(np.arange(n), np.arange(n))
    truth = classes((jj + 0.5) * t_res, (ii + 0.5) * t_res)
    gt = tmp_path / "drive.gt.npz"
    np.savez(gt, grid_origin_xy=np.array([0.0, 0.0]), grid_resolution_m=np.array(t_res), semantic=truth,
             elevation=np.zeros((n, n), np.float32))
    res, offset = 0.1, np.array([0.06, -0.04])
    m = int(size / res) - 2
    mj, mi = np.meshgrid(np.arange(m), np.arange(m))
    x0 = y0 = 0.1  # the map's cell centres on the truth's cell edges, as the bench's maps
    out = tmp_path / "map"
    out.mkdir()
    np.save(out / "bev_semantics.npy", classes(x0 + mj * res - offset[0], y0 + mi * res - offset[1]))
    np.save(out / "bev_elevation.npy", np.zeros((m, m), np.float32))
    (out / "bev.json").write_text(f'{{"origin_xy": [{x0}, {y0}], "resolution_m": {res}, "semantics_no_label": 255}}')
    figures = fixes_bench.registered_miou(out, gt)
    assert np.allclose(figures["fleet_shift_to_truth_cm"], -100 * offset, atol=1.6)  # fleet's estimate
    assert np.abs(np.subtract(figures["shift_to_truth_cm"], figures["fleet_shift_to_truth_cm"])).max() <= 3.01
    assert figures["miou_pct_registered"] > figures["miou_pct_raster"] + 10
    assert figures["miou_pct_registered"] > 85
