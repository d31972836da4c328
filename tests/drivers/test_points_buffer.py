"""The decoders' output arrays are reused only when nothing holds them (drivers/lidar/packet_decoding.py,
points_buffer): points a caller keeps never change under a later decode, and dropped ones give their memory back."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.velodyne_calibration import load_velodyne_calibration
from drivers.lidar.velodyne_decoder import VelodyneDecoder

DATA = Path("/work/shared/data/lidar_nebula")
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared lidar_nebula captures not present")


@pytest.fixture(scope="module")
def capture():
    payloads = [d.payload for d in read_pcap_udp(DATA / "velodyne" / "vlp32.pcap").datagrams]
    return load_velodyne_calibration(DATA / "calib" / "VLP32.yaml"), payloads[:200], payloads[200:]


def _copies(points) -> dict[str, np.ndarray]:
    return {name: getattr(points, name).copy() for name in ("xyz", "distance_m", "intensity", "laser_id", "ring",
                                                             "azimuth_cdeg", "return_type", "timestamp_ns",
                                                             "packet_index")}


def test_points_kept_by_the_caller_do_not_change_under_later_decodes(capture):
    calibration, first, second = capture
    kept = VelodyneDecoder(calibration).decode(first)
    before = _copies(kept)
    view = kept.xyz[5:50]  # a view alone holds the memory too
    view_before = view.copy()
    del kept
    for _ in range(3):
        VelodyneDecoder(calibration).decode(second)
    np.testing.assert_array_equal(view, view_before)
    kept = VelodyneDecoder(calibration).decode(first)
    again = VelodyneDecoder(calibration).decode(second)
    for name, values in before.items():
        np.testing.assert_array_equal(getattr(kept, name), values)
    assert again.xyz.base is not kept.xyz.base


def test_dropped_points_give_their_memory_to_the_next_decode_which_is_still_right(capture):
    calibration, first, second = capture
    expected = _copies(VelodyneDecoder(calibration).decode(second))
    points = VelodyneDecoder(calibration).decode(first)
    address = points.xyz.__array_interface__["data"][0]
    del points
    points = VelodyneDecoder(calibration).decode(second)
    assert points.xyz.__array_interface__["data"][0] == address
    for name, values in expected.items():
        np.testing.assert_array_equal(getattr(points, name), values)


def test_threads_decoding_at_once_each_get_their_own_points(capture):
    calibration, first, second = capture
    expected = {0: _copies(VelodyneDecoder(calibration).decode(first)),
                1: _copies(VelodyneDecoder(calibration).decode(second))}
    results: dict[int, list] = {0: [], 1: []}

    def work(which: int) -> None:
        for _ in range(20):
            results[which].append(VelodyneDecoder(calibration).decode((first, second)[which]))

    threads = [threading.Thread(target=work, args=(i,)) for i in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for which, decoded in results.items():
        for points in decoded:
            for name, values in expected[which].items():
                np.testing.assert_array_equal(getattr(points, name), values)
