import numpy as np

from mapping.inputs.static_ground import StaticGround, static_index


def _road(rng: np.random.Generator, n: int, scan: int) -> tuple[np.ndarray, np.ndarray]:
    xy = rng.uniform(0.0, 1.0, (n, 2))
    return np.column_stack([xy, rng.normal(0.0, 0.002, n)]), np.full(n, scan)


def test_a_passing_cars_low_points_are_dropped_and_static_raised_ground_is_kept():
    """Ten scans of a 1 m road patch. In scan 3 a car's side hides a strip, its lowest points 3-7 cm above the
    road (what one scan's filter keeps: the lowest of their cell in that scan); a 15 cm curb top along one edge
    is in every scan. The car's points go, the road and the curb top stay."""
    rng = np.random.default_rng(0)
    parts = [_road(rng, 400, s) for s in range(10)]
    car = np.column_stack([rng.uniform(0.2, 0.8, 60), rng.uniform(0.4, 0.5, 60), rng.uniform(0.03, 0.07, 60)])
    curb = [np.column_stack([rng.uniform(0.0, 1.0, 40), rng.uniform(1.0, 1.08, 40), np.full(40, 0.15)])
            for _ in range(10)]
    points = np.concatenate([p for p, _ in parts] + [car] + curb)
    scan = np.concatenate([s for _, s in parts] + [np.full(60, 3)] + [np.full(40, s) for s in range(10)])
    kept = np.zeros(len(points), bool)
    kept[static_index(points, scan, StaticGround())] = True
    road = np.arange(4000)
    car_ids = np.arange(4000, 4060)
    curb_ids = np.arange(4060, len(points))
    assert kept[road].mean() > 0.99
    assert kept[curb_ids].mean() > 0.95
    assert not kept[car_ids].any()


def test_ground_one_scan_saw_is_kept_where_it_is_the_lowest():
    points = np.array([[0.05, 0.05, 0.0], [0.05, 0.06, 0.01], [0.55, 0.05, 0.30]])
    assert static_index(points, np.array([0, 0, 1])).tolist() == [0, 1, 2]
    assert static_index(np.zeros((0, 3)), np.zeros(0, int)).tolist() == []
