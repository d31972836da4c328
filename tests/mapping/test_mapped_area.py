"""The mapped area (mapping.fits.mapped_area): the teeth of the views' reach left out, straight edges kept."""

from types import SimpleNamespace

import numpy as np

from mapping.fits.mapped_area import mapped_vertices
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.road_mesh import build_road_mesh
from mapping.outputs.map_metrics import edge_sawtooth_cm


def _drive():
    t = np.linspace(0.0, 10.0, 41)
    return build_road_mesh(HorizontalTrack(t, np.column_stack([4.0 * t, np.zeros_like(t), np.zeros_like(t)])),
                           15.0, 0.1, 1.5)


def _views(mesh, reach_m) -> np.ndarray:
    """Views per vertex: 3 within 8 m right of the 40 m track and up to reach_m(x) left of it, 1 beyond 7 m left."""
    x, y = mesh.xy[:, 0], mesh.xy[:, 1]
    seen = (y >= -8.0) & (y <= reach_m(x)) & (x >= 0.0) & (x <= 40.0)
    return np.where(seen, np.where(y > 7.0, 1, 3), 0)


def test_the_teeth_of_the_views_reach_are_left_out_and_the_area_inside_them_kept():
    mesh = _drive()
    views = _views(mesh, lambda x: 9.0 + 0.8 * (x % 1.0))  # one 0.8 m tooth per metre, as keyframes 1 m apart
    keep = mapped_vertices(mesh, views, 1, 1.0)
    before = edge_sawtooth_cm(SimpleNamespace(mesh=mesh, observed=views))
    after = edge_sawtooth_cm(SimpleNamespace(mesh=mesh, observed=keep.astype(np.int32)))
    assert before > 20.0 and after < 10.0, (before, after)  # measured 25.3 -> 2.7 cm
    assert not (keep & (views == 0)).any()
    inner = (views > 0) & (mesh.xy[:, 1] <= 9.0)  # the area under the teeth
    assert (keep & inner).sum() > 0.995 * inner.sum()  # all but the drive's rounded corners


def test_a_straight_edge_is_kept_and_too_few_views_are_not_mapped():
    mesh = _drive()
    views = _views(mesh, lambda x: np.full_like(x, 9.0))
    keep = mapped_vertices(mesh, views, 1, 1.0)
    assert keep.sum() > 0.995 * (views > 0).sum()
    assert np.array_equal(mapped_vertices(mesh, views, 1, 0.0), views > 0)  # no opening: every seen vertex
    two = mapped_vertices(mesh, views, 2, 0.0)
    assert np.array_equal(two, views >= 2) and mesh.xy[two, 1].max() <= 7.0
