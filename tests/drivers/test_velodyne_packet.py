"""Velodyne packet decoder against velodyne-decoder 3.1.0 (test-only oracle) on the real VLP-16 (dual
return), VLP-32C and VLS-128 captures in /work/shared/data/lidar_nebula, point by point; scan sizes
against the reference clouds; malformed input counted and skipped; the calibration loader's errors."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import velodyne_decoder as vd

from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.velodyne_calibration import load_velodyne_calibration
from drivers.lidar.velodyne_decoder import (
    PACKET_SIZE,
    RETURN_TYPE_LAST,
    RETURN_TYPE_STRONGEST,
    VelodyneDecoder,
)

DATA = Path("/work/shared/data/lidar_nebula")
CAPTURES = {  # capture: (calibration, model, the model's factory return-mode byte in the capture)
    "vlp16": ("VLP16", "VLP-16", 0x39),
    "vlp32": ("VLP32", "VLP-32C", 0x37),
    "vls128": ("VLS128", "VLS-128", 0x37),
}
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared lidar_nebula captures not present")


def _payloads(capture: str) -> list[tuple[int, bytes]]:
    return [(d.timestamp_ns, d.payload) for d in read_pcap_udp(DATA / "velodyne" / f"{capture}.pcap").datagrams]


def _reference_scans(capture: str, payloads: list[tuple[int, bytes]]) -> list[np.ndarray]:
    """velodyne-decoder's scans of the raw payloads: (M, 8) x y z intensity time column ring return_type."""
    config = vd.Config()
    config.calibration = vd.Calibration.read(str(DATA / "calib" / f"{CAPTURES[capture][0]}.yaml"))
    decoder = vd.StreamDecoder(config)
    scans = []
    for stamp_ns, payload in payloads:
        result = decoder.decode(stamp_ns * 1e-9, payload)
        if result is not None:
            scans.append(result[1])
    result = decoder.finish()
    if result is not None:
        scans.append(result[1])
    return scans


@pytest.fixture(scope="module", params=sorted(CAPTURES))
def decoded(request):
    capture = request.param
    payloads = _payloads(capture)
    calibration = load_velodyne_calibration(DATA / "calib" / f"{CAPTURES[capture][0]}.yaml")
    points = VelodyneDecoder(calibration).decode([p for _, p in payloads])
    return capture, payloads, points, _reference_scans(capture, payloads)


def test_decodes_every_packet_of_the_capture(decoded):
    capture, payloads, points, _ = decoded
    assert points.model == CAPTURES[capture][1]
    assert points.counts["packets_in"] == len(payloads)
    assert points.counts["packets_decoded"] == len(payloads)
    assert {p[1204] for _, p in payloads} == {CAPTURES[capture][2]}


def test_points_equal_velodyne_decoder(decoded):
    capture, _, points, scans = decoded
    ref = np.concatenate(scans)
    assert len(points.xyz) == len(ref) > 10_000
    np.testing.assert_allclose(points.xyz, ref[:, :3], rtol=0, atol=1e-4)
    np.testing.assert_array_equal(points.intensity, ref[:, 3])
    np.testing.assert_array_equal(points.ring, ref[:, 6].astype(np.uint16))
    np.testing.assert_array_equal(points.return_type, ref[:, 7].astype(np.uint8))
    # The laser id is the channel: its ring is the calibration's rank of that laser by elevation.
    calibration = load_velodyne_calibration(DATA / "calib" / f"{CAPTURES[capture][0]}.yaml")
    assert points.laser_id.max() == calibration.num_lasers - 1
    np.testing.assert_array_equal(calibration.ring[points.laser_id], points.ring)
    distance = np.linalg.norm(ref[:, :3].astype(np.float64), axis=1)
    np.testing.assert_allclose(points.distance_m, distance, atol=1e-4)


def test_point_times_equal_velodyne_decoder_within_each_scan(decoded):
    """velodyne-decoder gives time relative to its scan stamp; ours is sensor time past the hour, so
    within a scan the two differ by one constant."""
    capture, _, points, scans = decoded
    start = 0
    for scan in scans:
        ours = points.timestamp_ns[start : start + len(scan)] * 1e-9
        offset = scan[:, 4].astype(np.float64) - ours
        if capture == "vls128" and start == 0:
            # velodyne-decoder times the stream's first VLS-128 packet alone with a 2.89 us group
            # (its other packets, like ours, 2.66666 us): 12.7 us over that packet. Left out.
            offset = offset[points.packet_index[: len(scan)] > 0]
        assert np.ptp(offset) < 1e-6  # its packet stamps jitter by ~0.2 us across a scan
        start += len(scan)
    spans = [np.ptp(points.timestamp_ns[points.packet_index == i]) for i in (0, 1)]
    assert all(0 < s < 1.4e6 for s in spans)  # a packet spans well under 1.4 ms of firings


def _pcd_point_count(path: Path) -> int:
    with path.open("rb") as f:
        for line in f:
            if line.startswith(b"POINTS"):
                return int(line.split()[1])
    raise AssertionError(f"{path}: no POINTS line")


def test_full_rotations_are_the_size_of_the_reference_cloud(decoded):
    capture, _, points, _ = decoded
    reference = _pcd_point_count(DATA / "velodyne" / f"{capture}.reference.pcd")
    # Rotations: cut where the interpolated azimuth wraps from ~359.99 deg back to ~0.
    az = points.azimuth_cdeg.astype(np.int64)
    cuts = np.flatnonzero(np.diff(az) < -18000) + 1
    sizes = np.diff(cuts)
    assert len(sizes) >= 2
    # The reference clouds drop some returns (Nebula's own range and dual-return filters): within 15 %.
    assert np.all(np.abs(sizes / reference - 1) < 0.15), (sizes, reference)
    xyz = points.xyz[cuts[0] : cuts[1]]
    assert 1.0 < np.median(np.linalg.norm(xyz, axis=1)) < 60.0


def test_dual_return_pairs_give_last_and_strongest_points():
    payloads = [p for _, p in _payloads("vlp16")]
    calibration = load_velodyne_calibration(DATA / "calib" / "VLP16.yaml")
    points = VelodyneDecoder(calibration).decode(payloads)
    types = set(np.unique(points.return_type).tolist())
    assert types == {RETURN_TYPE_STRONGEST, RETURN_TYPE_LAST, RETURN_TYPE_STRONGEST | RETURN_TYPE_LAST}


def test_bad_packets_are_counted_and_skipped_and_the_good_ones_still_decode():
    good = [p for _, p in _payloads("vlp32")[:6]]
    calibration = load_velodyne_calibration(DATA / "calib" / "VLP32.yaml")
    alone = VelodyneDecoder(calibration).decode(good[:3] + good[4:])  # good[3] goes in only too long

    bad_flag = bytearray(good[1])
    bad_flag[300] = 0x00  # block 3's flag byte
    unknown_product = bytearray(good[2])
    unknown_product[1205] = 0x77
    unknown_mode = bytearray(good[2])
    unknown_mode[1204] = 0x10
    foreign = bytearray(good[3])
    foreign[1205] = 0xA1  # a VLS-128 packet where a VLP-32C is calibrated
    batch = [
        good[0],
        good[1][:700],  # truncated
        bytes(bad_flag),
        b"\x00" * 512,  # a position packet on the same port
        bytes(unknown_product),
        bytes(unknown_mode),
        bytes(foreign),
        good[1],
        good[2],
        good[3] + b"\x00",  # too long
        good[4],
        good[5],
    ]
    points = VelodyneDecoder(calibration).decode(batch)
    c = points.counts
    assert (c["packets_in"], c["packets_decoded"]) == (12, 5)
    assert (c["wrong_size"], c["bad_block_flag"], c["unknown_factory"], c["foreign_model"]) == (3, 1, 2, 1)
    assert c["packets_in"] == sum(v for k, v in c.items() if k != "packets_in")
    check = VelodyneDecoder(calibration).check(batch)
    np.testing.assert_array_equal(np.flatnonzero(check.accepted), [0, 7, 8, 10, 11])
    assert check.counts == {"wrong_size": 3, "bad_block_flag": 1, "unknown_factory": 2, "foreign_model": 1}
    np.testing.assert_array_equal(check.sensor_time_ns[check.accepted] // 1000,
                                  [int.from_bytes(good[i][1200:1204], "little") for i in (0, 1, 2, 4, 5)])
    np.testing.assert_array_equal(points.xyz, alone.xyz)
    np.testing.assert_array_equal(np.unique(points.packet_index), [0, 7, 8, 10, 11])
    assert len(np.unique(alone.packet_index)) == 5


def test_array_batch_of_wrong_width_is_counted_not_raised():
    calibration = load_velodyne_calibration(DATA / "calib" / "VLP16.yaml")
    points = VelodyneDecoder(calibration).decode(np.zeros((4, 1000), np.uint8))
    assert (points.counts["packets_in"], points.counts["wrong_size"], len(points.xyz)) == (4, 4, 0)
    garbage = np.random.default_rng(0).integers(0, 256, (50, PACKET_SIZE), dtype=np.uint8)
    points = VelodyneDecoder(calibration).decode(garbage)
    assert points.counts["packets_decoded"] == 0 and points.counts["packets_in"] == 50


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("num_lasers: 1\n", "missing key 'lasers'"),
        ("lasers: []\nnum_lasers: 1\n", "must list num_lasers=1"),
        ("lasers:\n- {laser_id: 0, vert_correction: 0.1}\nnum_lasers: 1\n", "has no 'rot_correction'"),
        ("lasers:\n- {laser_id: 0, rot_correction: x, vert_correction: 0}\nnum_lasers: 1\n", "rot_correction"),
        ("lasers:\n- {laser_id: 3, rot_correction: 0, vert_correction: 0}\nnum_lasers: 1\n", "laser_id=3"),
        ("lasers: [\n", "not valid YAML"),
    ],
)
def test_bad_calibration_names_file_and_key(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        load_velodyne_calibration(path)
    assert str(path) in str(err.value)


def test_calibration_reads_the_shared_files():
    for name, lasers in (("VLP16", 16), ("VLP32", 32), ("VLS128", 128)):
        calibration = load_velodyne_calibration(DATA / "calib" / f"{name}.yaml")
        assert calibration.num_lasers == lasers
        assert sorted(calibration.ring.tolist()) == list(range(lasers))
        assert np.all(np.abs(calibration.vert_correction_rad) < np.radians(30))


def test_a_batch_mixing_dual_and_single_return_packets_decodes_like_its_parts():
    dual = [p for _, p in _payloads("vlp16")[:6]]
    single = [bytes(p[:1204]) + bytes([0x38]) + p[1205:] for p in dual[3:]]  # relabelled "last return"
    calibration = load_velodyne_calibration(DATA / "calib" / "VLP16.yaml")
    mixed = VelodyneDecoder(calibration).decode(dual[:3] + single)
    first, second = VelodyneDecoder(calibration).decode(dual[:3]), VelodyneDecoder(calibration).decode(single)
    np.testing.assert_array_equal(mixed.xyz, np.concatenate([first.xyz, second.xyz]))
    np.testing.assert_array_equal(mixed.return_type, np.concatenate([first.return_type, second.return_type]))
    np.testing.assert_array_equal(mixed.timestamp_ns, np.concatenate([first.timestamp_ns, second.timestamp_ns]))
    assert set(second.return_type.tolist()) == {RETURN_TYPE_LAST}
    assert len(second.xyz) > len(first.xyz) * 1.5  # single return: every block its own firing, none merged


def test_vls128_dual_return_packets_ignore_their_four_empty_blocks():
    """No dual-return VLS-128 capture is shared: this checks the layout rule only (blocks 8-11 unused)."""
    packet = bytearray(_payloads("vls128")[5][1])
    packet[1204] = 0x39
    for block in range(8):  # dual layout: bank of block b is b // 2
        packet[block * 100 : block * 100 + 2] = int([0xEEFF, 0xDDFF, 0xCCFF, 0xBBFF][block // 2]).to_bytes(2, "little")
    calibration = load_velodyne_calibration(DATA / "calib" / "VLS128.yaml")
    points = VelodyneDecoder(calibration).decode([bytes(packet)])
    assert points.counts["packets_decoded"] == 1
    assert len(points.xyz) > 0
    assert set(points.laser_id.tolist()) <= set(range(128))
    blank = bytearray(packet)
    for block in range(8, 12):
        blank[block * 100 + 4 : block * 100 + 100] = bytes(96)
    again = VelodyneDecoder(calibration).decode([bytes(blank)])
    np.testing.assert_array_equal(points.xyz, again.xyz)


def test_a_vls128_stream_decoded_call_by_call_gives_the_points_of_one_call():
    """The rotation rate comes from the packet before, across calls too."""
    payloads = [p for _, p in _payloads("vls128")[:300]]
    calibration = load_velodyne_calibration(DATA / "calib" / "VLS128.yaml")
    whole = VelodyneDecoder(calibration).decode(payloads)
    decoder = VelodyneDecoder(calibration)
    parts = [decoder.decode(payloads[i : i + 70]) for i in range(0, len(payloads), 70)]
    np.testing.assert_array_equal(np.concatenate([p.xyz for p in parts]), whole.xyz)
    np.testing.assert_array_equal(np.concatenate([p.azimuth_cdeg for p in parts]), whole.azimuth_cdeg)


def test_decoders_made_anew_for_changed_calibrations_use_each_ones_values():
    """A decoder made again for a calibration seen before reuses its tables (made once per calibration); one whose
    per-laser values differ in any laser gets its own: its angles and its intensity limits, the others' unchanged."""
    payloads = [p for _, p in _payloads("vlp32")[:40]]
    calibration = load_velodyne_calibration(DATA / "calib" / "VLP32.yaml")
    first = VelodyneDecoder(calibration).decode(payloads)
    vert = calibration.vert_correction_rad.copy()
    vert[5] += np.radians(1.0)
    top = calibration.max_intensity.copy()
    top[6] = 20.0
    changed = replace(calibration, vert_correction_rad=vert, max_intensity=top)
    second = VelodyneDecoder(changed).decode(payloads)
    again = VelodyneDecoder(calibration).decode(payloads)
    laser5, laser6 = first.laser_id == 5, first.laser_id == 6
    assert laser5.sum() > 100 and (first.intensity[laser6] > 20).sum() > 10
    assert np.all(second.xyz[laser5, 2] > first.xyz[laser5, 2])  # 1 degree higher: z up at every range
    np.testing.assert_array_equal(second.xyz[~laser5], first.xyz[~laser5])
    np.testing.assert_array_equal(second.intensity[laser6], np.minimum(first.intensity[laser6], 20.0))
    np.testing.assert_array_equal(second.intensity[~laser6], first.intensity[~laser6])
    for name in ("xyz", "intensity", "timestamp_ns", "ring"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
