"""The pooled held-out figures of mapping/outputs/map_metrics.py: PSNR by distance band and the saturation ratio,
on views whose errors and colours are known."""

from __future__ import annotations

import numpy as np

from mapping.outputs.map_metrics import DISTANCE_BANDS_M, _pooled, _saturation, _ViewScore


def _score(errors_by_band: list[tuple[float, int]], rendered_sat: float, observed_sat: float, pixels: int):
    """A view whose band k holds n pixels (3 channels each) of squared error e per channel."""
    return _ViewScore(None, np.array([3 * n * e for e, n in errors_by_band], float),
                      np.array([3 * n for _, n in errors_by_band], float),
                      np.array([rendered_sat * pixels, observed_sat * pixels]), pixels)


def test_distance_bands_pool_the_squared_errors_of_every_view():
    near = _score([(1e-3, 100), (1e-2, 50), (0.0, 0), (0.0, 0)], 0.2, 0.4, 150)
    far = _score([(1e-3, 300), (1e-4, 50), (1e-2, 10), (0.0, 0)], 0.3, 0.3, 360)
    pooled = _pooled([near, far])
    bands = pooled["psnr_by_distance_db"]
    assert list(bands) == ["0-10 m", "10-20 m", "20-40 m", "40+ m"] and len(bands) == len(DISTANCE_BANDS_M)
    assert abs(bands["0-10 m"] - 30.0) < 1e-9  # MSE 1e-3 in both views
    assert abs(bands["10-20 m"] - 10 * np.log10(1 / ((50 * 1e-2 + 50 * 1e-4) / 100))) < 1e-9
    assert abs(bands["20-40 m"] - 20.0) < 1e-9 and bands["40+ m"] is None
    assert abs(pooled["saturation_rendered_pct"] - 100 * (0.2 * 150 + 0.3 * 360) / 510) < 1e-9
    assert abs(pooled["saturation_ratio"] - (0.2 * 150 + 0.3 * 360) / (0.4 * 150 + 0.3 * 360)) < 1e-12


def test_saturation_is_hsv_s_and_nothing_seen_gives_none():
    rgb = np.array([[1.0, 0.5, 0.5], [0.2, 0.2, 0.2], [0.0, 0.0, 0.0], [0.0, 0.8, 0.4]])
    np.testing.assert_allclose(_saturation(rgb), [0.5, 0.0, 0.0, 1.0])
    assert _pooled([]) == {"psnr_by_distance_db": None, "saturation_rendered_pct": None,
                           "saturation_observed_pct": None, "saturation_ratio": None}
