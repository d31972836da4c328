"""What a keyframe observes in the fast fit (mapping.fits.fast_fit.flat_topped_reach): a forward camera's view cut
off ahead is a wedge; keyframes one metre apart then leave a saw-tooth edge on the mapped area, one tooth per
keyframe, unless each view's lateral reach is capped where it still holds for two spacings."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mapping.fits.fast_fit import flat_topped_reach
from mapping.fits.vertex_observations import project_points
from mapping.localization.trajectory import HorizontalTrack
from mapping.method.road_mesh import build_road_mesh, track_offsets
from mapping.method.scene_data import CameraModel, Keyframe
from mapping.outputs.map_metrics import edge_sawtooth_cm

CAMERA = CameraModel("front", np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]]),
                     (0.0, 0.0, 0.0, 0.0, 0.0), 1242, 375)  # KITTI's colour camera: 81 degrees across
AHEAD_M, SPACING_M = 12.0, 1.0


def _keyframe(x: float) -> Keyframe:
    """The camera 1.65 m above the road at x, looking along +x (camera x right = world -y, y down = world -z)."""
    t = np.eye(4)
    t[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    t[:3, 3] = (x, 0.0, 1.65)
    return Keyframe("front", x, t, np.zeros((375, 1242, 3), np.uint8), None)


def _mapped(capped: bool) -> SimpleNamespace:
    t = np.linspace(0.0, 40.0, 41)
    track = HorizontalTrack(t, np.column_stack([t, np.zeros_like(t), np.zeros_like(t)]))
    mesh = build_road_mesh(track, 15.0, 0.1, 1.65)
    s, lateral = track_offsets(track, mesh.xy)
    points = np.column_stack([mesh.xy, np.zeros(mesh.num_vertices)])
    observed = np.zeros(mesh.num_vertices, np.int32)
    for x in np.arange(0.0, 28.0, SPACING_M):
        kf = _keyframe(x)
        reach = (s >= x - 3.0) & (s <= x + AHEAD_M)
        _, visible = project_points(points, CAMERA, kf.T_world_camera)
        if capped:
            visible &= flat_topped_reach(points, s <= x + AHEAD_M - 2 * SPACING_M, lateral, kf, CAMERA)
        observed[reach & visible] += 1
    return SimpleNamespace(mesh=mesh, observed=observed, lateral=lateral)


def test_capped_reaches_leave_a_straight_edge_where_wedges_leave_a_saw_tooth():
    wedges, capped = _mapped(False), _mapped(True)
    assert edge_sawtooth_cm(wedges) > 20.0  # the teeth: 0.86 m deep, one per metre, on both sides
    assert edge_sawtooth_cm(capped) < 10.0
    # the cap is where the view still reaches 2 m short of its far end, 10 m ahead: on the left (image columns
    # left of cx) 10 x 609.6 / 721.5 m, on the right 10 x (1241 - 609.6) / 721.5 m
    for side, columns in ((1.0, 609.6), (-1.0, 1241.0 - 609.6)):
        far = (capped.observed > 0) & (side * capped.lateral > 0)
        assert abs(np.abs(capped.lateral[far]).max() - 10.0 * columns / 721.5) < 0.15
