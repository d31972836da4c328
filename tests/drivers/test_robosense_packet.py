"""RoboSense decoder: the real Helios-16P capture in /work/shared/data/lidar_nebula against that project's own
decoded cloud of its first rotation, point by point; bad and DIFOP packets counted and skipped; Ruby-128 on
packets this test encodes itself (no capture is shared) with a self-made angle table, against geometry
computed here in float64 from the MSOP layout; the angle file's and the factory's errors."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np
import pytest

from drivers.lidar.packet_decoding import RETURN_TYPE_OTHER, RETURN_TYPE_STRONGEST, rotation_starts
from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.robosense_calibration import load_robosense_calibration
from drivers.lidar.robosense_decoder import HELIOS16P, ROBOSENSE_MODELS, RobosenseDecoder, robosense_decoder

DATA = Path("/work/shared/data/lidar_nebula")
HELIOS_CSV = DATA / "calib" / "RobosenseHelios16P.csv"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared lidar_nebula captures not present")


def _helios_payloads() -> list[bytes]:
    return [d.payload for d in read_pcap_udp(DATA / "robosense" / "helios16P.pcap").datagrams]


def _reference() -> np.ndarray:
    """Nebula's cloud: x y z intensity return_type channel azimuth elevation distance time_stamp."""
    return np.loadtxt(DATA / "robosense" / "helios16P.reference.pcd", skiprows=11)


@pytest.fixture(scope="module")
def helios():
    payloads = _helios_payloads()
    return payloads, robosense_decoder("robosense-helios16p", HELIOS_CSV).decode(payloads)


@needs_data
def test_helios_decodes_every_data_packet_and_counts_the_difop_one(helios):
    payloads, points = helios
    assert points.model == "robosense-helios16p"
    assert points.counts["packets_in"] == len(payloads) == 751
    assert (points.counts["packets_decoded"], points.counts["difop"]) == (750, 1)  # DIFOP at index 543
    assert 543 not in set(points.packet_index.tolist())


@needs_data
def test_helios_first_rotation_equals_the_reference_point_by_point(helios):
    """The reference is the capture's first rotation, from its first packet, in the same order: rings
    (Nebula's channel is the rank by elevation), intensities and distances equal; xyz within 2 mm for 99 %
    of the points. The largest errors (~3 cm, 24 of 15,258 points over 1 cm, all at 49-152 m) come from
    the azimuth interpolation (Nebula's Helios-16P firing table differs from rs_driver's, used here, by up
    to 0.02 degrees) and from laser 3's elevation (see the next test)."""
    _, points = helios
    ref = _reference()
    n = len(ref)
    np.testing.assert_array_equal(points.ring[:n], ref[:, 5].astype(np.uint16))
    np.testing.assert_array_equal(points.intensity[:n], ref[:, 3])
    np.testing.assert_allclose(points.distance_m[:n], ref[:, 8], atol=1e-5)
    error = np.abs(points.xyz[:n].astype(np.float64) - ref[:, :3]).max(axis=1)
    assert np.median(error) < 1e-4
    assert np.quantile(error, 0.99) < 2e-3
    assert np.mean(error > 0.01) < 0.002
    assert error.max() < 0.05
    assert np.all(points.distance_m[:n][error > 0.01] > 45)
    # Sign check: the reference and ours agree on left (y > 0) and up (z > 0) point by point.
    far = ref[:, 8] > 2
    assert np.all(np.sign(points.xyz[:n][far, 1]) == np.sign(ref[far, 1]))


# Nebula's own Helios-16P firing times (us; it spreads the 32 channels over two 55.56 us cycles and halves
# the azimuth step for it) and its reading of the angle file (each value times 100, truncated in float32:
# 8.90 becomes 889), read from its source at the reference's commit.
NEBULA_FIRING_US = [0.00, 3.15, 6.30, 9.45, 13.26, 17.08, 20.56, 23.71, 26.53, 27.77, 31.49, 32.73, 36.46, 38.94,
                    41.42, 43.91, 55.56, 58.70, 61.85, 65.00, 68.82, 72.64, 76.12, 79.27, 82.08, 83.32, 87.05, 88.29,
                    92.01, 94.50, 96.98, 99.46]


@needs_data
def test_helios_with_nebulas_constants_reproduces_its_cloud_exactly():
    """What separates ours from the reference is only those two constants: with them, every point agrees."""
    angles = np.loadtxt(HELIOS_CSV, delimiter=",", dtype=np.float32)
    calibration = dataclasses.replace(
        load_robosense_calibration(HELIOS_CSV),
        elevation_cdeg=np.trunc(angles[:, 0] * np.float32(100)).astype(np.int32),
    )
    model = dataclasses.replace(HELIOS16P, firing_s=np.array(NEBULA_FIRING_US) * 1e-6 / 2)
    points = RobosenseDecoder(model, calibration).decode(_helios_payloads())
    ref = _reference()
    error = np.abs(points.xyz[: len(ref)].astype(np.float64) - ref[:, :3]).max(axis=1)
    assert error.max() < 1e-5


@needs_data
def test_helios_rotations_are_the_size_of_the_reference(helios):
    _, points = helios
    reference = len(_reference())
    cuts = rotation_starts(points.azimuth_cdeg)
    sizes = np.diff(cuts)
    assert len(sizes) >= 3
    # Nebula closes a rotation at a block's azimuth, ours at each point's: a few points apart.
    assert abs(cuts[0] - reference) < 50
    assert np.all(np.abs(sizes / reference - 1) < 0.05), (sizes, reference)


@needs_data
def test_helios_fields(helios):
    payloads, points = helios
    assert set(points.laser_id.tolist()) == set(range(16))
    assert set(points.return_type.tolist()) == {RETURN_TYPE_STRONGEST}
    assert payloads[543][300] == 0x04  # its DIFOP's return mode (rs_driver's Helios layout): single, strongest
    assert points.distance_m.min() >= 0.2
    az = points.azimuth_cdeg.astype(np.int64)
    assert np.all(az < 36000) and len(rotation_starts(az)) == 5  # ~4.7 turns at 10 Hz
    # Times: the header's UTC (seconds + microseconds) plus 55.56 us a block and 1.73 us a channel.
    check = robosense_decoder("robosense-helios16p", HELIOS_CSV).check(payloads)
    stamps = check.sensor_time_ns[check.accepted]
    assert np.all(stamps // 1_000_000_000 == 1483724884)  # 2017-01-06, as the reference's time_stamp
    assert 660_000 < np.median(np.diff(stamps)) < 675_000  # 12 blocks of 55.56 us
    first = points.packet_index == 0
    offsets = points.timestamp_ns[first] - stamps[0]
    assert 0 <= offsets.min() and offsets.max() < 667_000
    assert np.all(np.diff(check.azimuth_cdeg[check.accepted][:140]) > 0)


@needs_data
def test_bad_packets_are_counted_and_the_good_ones_still_decode(tmp_path):
    payloads = _helios_payloads()
    good = payloads[:5]
    bad_block = bytearray(good[1])
    bad_block[42 + 5 * 100] = 0x00  # block 5's id
    bad_header = bytearray(good[2])
    bad_header[0] = 0x54
    bad_time = bytearray(good[3])
    bad_time[26:30] = (2_000_000).to_bytes(4, "big")
    batch = [good[0], good[1][:1000], bytes(bad_block), payloads[543], bytes(bad_header), bytes(bad_time),
             good[1], good[2] + b"\x00", good[3], good[4]]
    decoder = robosense_decoder("robosense-helios16p", HELIOS_CSV)
    points = decoder.decode(batch)
    c = points.counts
    assert (c["packets_in"], c["packets_decoded"]) == (10, 4)
    assert (c["wrong_size"], c["bad_block_flag"], c["difop"], c["bad_header"], c["bad_time"]) == (2, 1, 1, 1, 1)
    check = decoder.check(batch)
    np.testing.assert_array_equal(np.flatnonzero(check.accepted), [0, 6, 8, 9])
    assert check.counts == {"wrong_size": 2, "bad_block_flag": 1, "difop": 1, "bad_header": 1, "bad_time": 1}
    alone = robosense_decoder("robosense-helios16p", HELIOS_CSV).decode([good[0], good[1], good[3], good[4]])
    np.testing.assert_array_equal(points.xyz, alone.xyz)
    np.testing.assert_array_equal(points.timestamp_ns, alone.timestamp_ns)
    # A Ruby-128 decoder takes no Helios packet: its blocks do not open with 0xFE.
    ruby = robosense_decoder("robosense-ruby128", _write_ruby_table(tmp_path / "ruby128.csv"))
    assert ruby.decode(good).counts["bad_block_flag"] == 5


@needs_data
def test_helios_dual_return_labels_the_second_half_of_each_block():
    points = robosense_decoder("robosense-helios16p", HELIOS_CSV, dual_return=True).decode(_helios_payloads()[:3])
    upper = points.laser_id  # channel % 16 either way
    assert set(upper.tolist()) <= set(range(16))
    assert set(points.return_type.tolist()) == {RETURN_TYPE_STRONGEST, RETURN_TYPE_OTHER}


# Ruby-128 ---------------------------------------------------------------------------------------------------


def ruby_angles() -> tuple[np.ndarray, np.ndarray]:
    """A self-made Ruby-128 table (no unit's file is shared): elevations -25..+15 degrees in 128 steps of
    40/127 degrees, given to the channels in a scrambled order (ring of channel c: 37 c mod 128), and azimuth
    offsets by the channel's place in its group of four: -2.5, -0.8, +0.8, +2.5 degrees."""
    channel = np.arange(128)
    ring = (37 * channel) % 128
    elevation = np.round(-25 + 40 * ring / 127, 2)
    azimuth = np.array([-2.5, -0.8, 0.8, 2.5])[channel % 4]
    return elevation, azimuth


def _write_ruby_table(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    elevation, azimuth = ruby_angles()
    path.write_text("".join(f"{e:.2f},{a:.2f}\n" for e, a in zip(elevation, azimuth, strict=True)))
    return path


def encode_ruby128(n_packets: int, seed: int = 0, dual: bool = False) -> tuple[list[bytes], np.ndarray, np.ndarray]:
    """Self-made Ruby-128 MSOP packets as rs_driver's layout has them: an 80-byte header (MSOP id, UTC
    seconds and microseconds at byte 10), 3 blocks (0xFE, return id, azimuth, 128 x (range, intensity)),
    4 tail bytes; 20 hundredths of a degree a firing (600 rpm). Dual: each firing's two returns in two
    blocks of one azimuth, so that packets alternate AAB and ABB. Returns the packets, the raw ranges
    (n, 3, 128) and the block azimuths (n, 3)."""
    rng = np.random.default_rng(seed)
    raw = rng.integers(100, 49000, (n_packets, 3, 128))
    raw[rng.random(raw.shape) < 0.15] = 0
    firing = np.arange(n_packets * 3) // (2 if dual else 1)
    azimuth = (35000 + 20 * firing).reshape(n_packets, 3) % 36000  # wraps once
    packets = []
    for p in range(n_packets):
        header = bytearray(80)
        header[0:4] = b"\x55\xaa\x05\x5a"
        microseconds = 250_000 + p * 167 if not dual else 250_000 + round((p * 3 // 2) * 55.55)
        header[10:16] = (1_700_000_000).to_bytes(6, "big")
        header[16:20] = microseconds.to_bytes(4, "big")
        out = bytearray(header)
        for b in range(3):
            out += bytes([0xFE, 0x00]) + int(azimuth[p, b]).to_bytes(2, "big")
            for c in range(128):
                out += struct.pack(">HB", int(raw[p, b, c]), (b * 128 + c) % 256)
        out += bytes(4)
        packets.append(bytes(out))
    return packets, raw, azimuth


def expected_ruby128_points(raw: np.ndarray, azimuth: np.ndarray, dual: bool = False) -> np.ndarray:
    """The points of encode_ruby128's packets, one by one in float64: (M, 9) x y z distance channel
    firing-azimuth packet time-ns return-type. Group g of four channels fires 3.236 us x g after its block's
    firing (55.55 us a firing); the azimuth moves on by the step to the packet's next firing (20 where there
    is none) in that proportion, truncated to 0.01 degrees; the lens sits 36.15 mm from the axis (RoboSense's
    RX). Dual: the first block of a firing is the strongest return (1), the second the last (2)."""
    elevation, offset = ruby_angles()
    expected = []
    for p in range(raw.shape[0]):
        firings = [(3 * p + b) // 2 if dual else 3 * p + b for b in range(3)]
        stamp_ns = 1_700_000_000_000_000_000 + 1000 * (250_000 + (round(firings[0] * 55.55) if dual else p * 167))
        for b in range(3):
            later = [k for k in range(3) if firings[k] == firings[b] + 1]
            step = (int(azimuth[p, later[0]]) - int(azimuth[p, b])) % 36000 if later else 20
            return_type = (1 if (3 * p + b) % 2 == 0 else 2) if dual else 1
            for c in range(128):
                d = raw[p, b, c] * 0.005
                if raw[p, b, c] == 0 or not 0.4 <= d <= 250:
                    continue
                t = (c % 64) // 4 * 3.236e-6
                fire = int(azimuth[p, b]) + int(step * t / 55.55e-6)
                a, a0, e = np.radians((fire + offset[c] * 100) / 100), np.radians(fire / 100), np.radians(elevation[c])
                x = d * np.cos(e) * np.cos(a) + 0.03615 * np.cos(a0)
                y = -d * np.cos(e) * np.sin(a) - 0.03615 * np.sin(a0)
                time_ns = stamp_ns + round(((firings[b] - firings[0]) * 55.55e-6 + t) * 1e9)
                expected.append((x, y, d * np.sin(e), d, c, fire % 36000, p, time_ns, return_type))
    return np.array(expected)


@pytest.mark.parametrize("dual", [False, True])
def test_ruby128_equals_geometry_computed_from_the_layout(tmp_path, dual):
    packets, raw, azimuth = encode_ruby128(40, dual=dual)
    decoder = robosense_decoder("robosense-ruby128", _write_ruby_table(tmp_path / "ruby128.csv"), dual_return=dual)
    points = decoder.decode(packets)
    assert points.counts["packets_decoded"] == 40
    expected = expected_ruby128_points(raw, azimuth, dual)
    assert len(points.xyz) == len(expected) > 10_000
    np.testing.assert_allclose(points.xyz, expected[:, :3], rtol=0, atol=1e-4)
    np.testing.assert_allclose(points.distance_m, expected[:, 3], rtol=1e-6)
    np.testing.assert_array_equal(points.laser_id, expected[:, 4])
    np.testing.assert_array_equal(points.azimuth_cdeg, expected[:, 5])
    np.testing.assert_array_equal(points.packet_index, expected[:, 6])
    np.testing.assert_allclose(points.timestamp_ns, expected[:, 7], atol=1)
    np.testing.assert_array_equal(points.return_type, expected[:, 8])
    np.testing.assert_array_equal(points.ring, (37 * points.laser_id.astype(np.int64)) % 128)
    assert len(rotation_starts(points.azimuth_cdeg)) == 1


def test_ruby128_check_gives_stamps_and_first_azimuths(tmp_path):
    packets, _, azimuth = encode_ruby128(5)
    decoder = robosense_decoder("robosense-ruby128", _write_ruby_table(tmp_path / "ruby128.csv"))
    check = decoder.check(packets + [packets[0][:80]])
    assert check.accepted.tolist() == [True] * 5 + [False]
    np.testing.assert_array_equal(check.azimuth_cdeg[:5], azimuth[:, 0])
    np.testing.assert_array_equal(check.sensor_time_ns[:5], 1_700_000_000_250_000_000 + np.arange(5) * 167_000)


@pytest.mark.parametrize(
    ("text", "message"),
    [("1.0,2.0\nabc,1\n", r":2: 'abc' is not a number"), ("1,2,3\n", ":1: expected 'elevation,azimuth'"),
     ("95,0\n", ":1: angle 95.0"), ("\n\n", "no laser angles")],
)
def test_bad_angle_file_names_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        load_robosense_calibration(path)
    assert str(path) in str(err.value)


def test_factory_checks_model_and_laser_count(tmp_path):
    assert ROBOSENSE_MODELS == ("robosense-helios16p", "robosense-ruby128")
    ruby_table = _write_ruby_table(tmp_path / "ruby128.csv")
    with pytest.raises(ValueError, match="128 lasers, but robosense-helios16p has 16"):
        robosense_decoder("robosense-helios16p", ruby_table)
    with pytest.raises(ValueError, match="unknown RoboSense model"):
        robosense_decoder("robosense-bpearl", ruby_table)
    with pytest.raises(ValueError, match="angle calibration file is needed"):
        robosense_decoder("robosense-ruby128", None)
