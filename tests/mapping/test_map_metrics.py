"""The pooled held-out figures of mapping/outputs/map_metrics.py: PSNR by distance band and the saturation ratio,
on views whose errors and colours are known; the artefact checks (saw-tooth edges, smears) on mapped areas and
views made to have them or not."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mapping.localization.trajectory import HorizontalTrack
from mapping.method.road_mesh import build_road_mesh
from mapping.outputs.map_metrics import (
    DISTANCE_BANDS_M,
    _pooled,
    _saturation,
    _ViewScore,
    edge_sawtooth_cm,
    smear_pct,
)


def _score(errors_by_band: list[tuple[float, int]], rendered_sat: float, observed_sat: float, pixels: int):
    """A view whose band k holds n pixels (3 channels each) of squared error e per channel."""
    return _ViewScore(None, np.array([3 * n * e for e, n in errors_by_band], float),
                      np.array([3 * n for _, n in errors_by_band], float),
                      np.array([rendered_sat * pixels, observed_sat * pixels]), pixels, np.zeros(0, np.int64),
                      np.zeros(0))


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


def _mapped_area(reach_m) -> SimpleNamespace:
    """A 40 m straight drive's mesh with the vertices observed within reach_m(x) of the track on its left and
    within 8 m on its right (a road map as edge_sawtooth_cm reads it)."""
    t = np.linspace(0.0, 10.0, 41)
    mesh = build_road_mesh(HorizontalTrack(t, np.column_stack([4.0 * t, np.zeros_like(t), np.zeros_like(t)])),
                           15.0, 0.1, 1.5)
    x, y = mesh.xy[:, 0], mesh.xy[:, 1]
    observed = ((y >= -8.0) & (y <= reach_m(x)) & (x >= 0.0) & (x <= 40.0)).astype(np.int32)
    return SimpleNamespace(mesh=mesh, observed=observed)


def test_a_saw_tooth_edge_measures_its_teeth_and_a_straight_one_about_a_cell():
    straight = edge_sawtooth_cm(_mapped_area(lambda x: np.full_like(x, 9.0)))
    curved = edge_sawtooth_cm(_mapped_area(lambda x: 9.0 + 2.0 * np.sin(x / 6.0)))
    teeth = edge_sawtooth_cm(_mapped_area(lambda x: 9.0 + 0.8 * (x % 1.0)))  # one 0.8 m tooth per metre
    assert straight < 10.0 and curved < 10.0, (straight, curved)  # measured 7.2 and 7.9 cm: the cells
    assert teeth > 20.0, teeth  # measured 25.3 cm: the teeth on one of the two edges
    assert edge_sawtooth_cm(SimpleNamespace(mesh=_mapped_area(np.zeros_like).mesh,
                                            observed=np.zeros(1, np.int32)[:0])) is None


def _residuals(*by_vertex: tuple[int, float]) -> _ViewScore:
    return _ViewScore(None, np.zeros(4), np.zeros(4), np.zeros(2), 0, np.array([v for v, _ in by_vertex]),
                      np.array([r for _, r in by_vertex]))


def test_smears_are_vertices_most_views_contradict_and_one_contradicting_view_is_not():
    views = [_residuals((0, 0.02), (1, 0.3), (2, 0.4), (3, 0.01)),  # vertex 2: something in front in this view
             _residuals((0, 0.03), (1, 0.25), (2, 0.02), (3, 0.5)),
             _residuals((0, 0.01), (1, 0.02), (2, 0.03)),
             _residuals((0, 0.02), (1, 0.2), (2, 0.01))]
    # vertex 1 (3 of 4 views against the map) is a smear, 0 and 2 are not, 3 (2 views) is not judged
    assert abs(smear_pct(views) - 100.0 / 3.0) < 1e-9
    assert smear_pct([]) is None and smear_pct(views[:2]) is None
