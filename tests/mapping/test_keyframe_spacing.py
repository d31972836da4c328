"""The shared input rules: keyframe spacing by distance travelled, and Lidar scan thinning."""

from mapping.inputs.lidar_ground import keeps_scan
from mapping.localization.keyframe_spacing import spaced_by_distance, spaced_preferring


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


def test_a_frame_without_a_mask_gives_way_to_one_with_a_mask_within_the_spacing_and_is_kept_otherwise():
    distances = [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0]
    masked = {0, 3, 5, 7}  # a segmenter slower than the camera that stops after frame 7
    kept = spaced_preferring(list(range(len(distances))), lambda i: distances[i], 1.0, lambda i: i in masked)
    # 2 (1.0 m) waits for 3 (1.5 m); 5 (2.5 m); 7 (3.5 m); no mask follows 9 and 11: they are kept without one
    assert kept == [0, 3, 5, 7, 9, 11]
    none = spaced_preferring(list(range(len(distances))), lambda i: distances[i], 1.0, lambda i: False)
    every = spaced_preferring(list(range(len(distances))), lambda i: distances[i], 1.0, lambda i: True)
    assert none == every == list(spaced_by_distance(range(len(distances)), lambda i: distances[i], 1.0))
    assert spaced_preferring([], lambda i: 0.0, 1.0, lambda i: True) == []


def test_every_nth_scan_from_the_first():
    kept = [n for n in range(12) if keeps_scan(n, 2, 3)]
    assert kept == [0, 1, 6, 7]
    assert all(keeps_scan(n, 4, 1) for n in range(10))
