"""The shared input rules: keyframe spacing by distance travelled, and Lidar scan thinning."""

from mapping.inputs.lidar_ground import keeps_scan
from mapping.localization.keyframe_spacing import spaced_by_distance


def test_a_frame_each_time_the_vehicle_has_moved_the_spacing():
    distances = [0.0, 0.4, 1.0, 1.5, 2.0, 2.9, 3.0]
    kept = list(spaced_by_distance(range(len(distances)), lambda i: distances[i], 1.0))
    assert kept == [0, 2, 4, 6]
    assert list(spaced_by_distance(range(len(distances)), lambda i: distances[i], 0.0)) == list(range(7))


def test_a_frame_refused_is_passed_over_and_the_next_one_tried():
    distances = [0.0, 1.0, 1.2, 2.0]
    asked = []

    def usable(i: int) -> bool:
        asked.append(i)
        return i != 1

    assert list(spaced_by_distance(range(4), lambda i: distances[i], 1.0, usable)) == [0, 2]
    assert asked == [0, 1, 2]  # frame 3 is only 0.8 m past frame 2: never asked


def test_every_nth_scan_from_the_first():
    kept = [n for n in range(12) if keeps_scan(n, 2, 3)]
    assert kept == [0, 1, 6, 7]
    assert all(keeps_scan(n, 4, 1) for n in range(10))
