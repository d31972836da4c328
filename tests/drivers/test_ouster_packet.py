"""Ouster packet codec against ouster-sdk 1.0 (test-only oracle) on the real captures in
/work/shared/data/ouster, plus encoder round trips, packet loss, malformed input and fuzzing."""

from __future__ import annotations

import hashlib
import json
import socket
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.lidar.lidar_points import LidarPacketBatch, batch_xyz, destagger, scan_point_cloud
from drivers.lidar.ouster_decoder import (
    count_missing_packets,
    decode_packets,
    newest_packet,
    ouster_scan_assembler,
    packet_sequence,
)
from drivers.lidar.ouster_encoder import encode_frame_packets, packet_frame_id, renumbered_packet
from drivers.lidar.ouster_metadata import metadata_to_json, parse_metadata, simulated_os128_metadata
from drivers.lidar.ouster_packet_layout import PROFILE_PIXEL_FIELDS, packet_layout
from drivers.lidar.ouster_xyz import make_xyz_lut
from drivers.lidar.pcap_udp import read_pcap_udp

sdk = pytest.importorskip("ouster.sdk.core")

DATA = Path("/work/shared/data/ouster")
CAPTURES = {  # metadata JSON stem -> pcap stem
    "OS-0-128-U1_v2.3.0_1024x10": "OS-0-128-U1_v2.3.0_1024x10",  # RNG15_RFL8_NIR8
    "OS-0-32-U1_v2.2.0_1024x10": "OS-0-32-U1_v2.2.0_1024x10",  # RNG19_RFL8_SIG16_NIR16_DUAL
    "OS-1-128_767798045_1024x10_20230712_120049": "OS-1-128_767798045_1024x10_20230712_120049",  # FuSa
    "OS-1-128_v2.3.0_1024x10": "OS-1-128_v2.3.0_1024x10_lb_n3",  # RNG15_RFL8_NIR8, 3 frames
    "OS-2-128-U1_v2.3.0_1024x10": "OS-2-128-U1_v2.3.0_1024x10",  # RNG19_RFL8_SIG16_NIR16
}
SDK_FIELDS = {
    "range_mm": "RANGE",
    "reflectivity": "REFLECTIVITY",
    "signal": "SIGNAL",
    "near_ir": "NEAR_IR",
    "range2_mm": "RANGE2",
    "reflectivity2": "REFLECTIVITY2",
    "signal2": "SIGNAL2",
}
XYZ = {"rtol": 2.5e-7, "atol": 1e-4}  # our float32 against the SDK's float64: 0.1 mm + ~2 ulp


def _load(stem: str):
    text = (DATA / f"{stem}.json").read_text()
    meta = parse_metadata(text)
    return text, meta, packet_layout(meta)


def _capture_payloads(pcap_stem: str, port: int | None = 7502) -> list[bytes]:
    return [d.payload for d in read_pcap_udp(DATA / f"{pcap_stem}.pcap", port).datagrams]


def _sdk_frames(info, payloads: list[bytes]) -> list:
    """Frames the SDK's FrameBatcher makes of the packets; a copy of the last packet with the
    next frame id releases the last frame, however incomplete."""
    fmt = sdk.PacketFormat(info)
    batcher = sdk.FrameBatcher(info)
    batcher.set_max_cache_size(1)
    packets = []
    for i, payload in enumerate(payloads):
        packet = sdk.LidarPacket(fmt)
        packet.buf[:] = np.frombuffer(payload, np.uint8)
        packet.host_timestamp = i + 1
        packets.append(packet)
    release = sdk.LidarPacket(fmt)
    release.buf[:] = packets[-1].buf
    fmt.set_frame_id(release, (fmt.frame_id(np.asarray(packets[-1].buf)) + 1) % (fmt.max_frame_id + 1))
    release.host_timestamp = len(packets) + 1
    frames, frame = [], sdk.LidarFrame(info)
    for packet in packets + [release]:
        if batcher.batch(packet, frame):
            frames.append(frame)
            frame = sdk.LidarFrame(info)
    return frames


# ---------------------------------------------------------------- metadata


@pytest.mark.parametrize("stem", sorted(p.stem for p in DATA.glob("*.json") if "digest" not in p.stem))
def test_metadata_parses_like_sdk(stem):
    text, meta, _ = _load(stem)
    info = sdk.SensorInfo(text)
    assert (meta.columns_per_frame, meta.pixels_per_column) == (info.w, info.h)
    assert meta.columns_per_packet == info.format.columns_per_packet
    assert meta.init_id == info.init_id and meta.prod_sn == str(info.sn)
    assert meta.header_type == info.format.header_type.name
    assert list(meta.column_window) == list(info.format.column_window)
    np.testing.assert_array_equal(meta.pixel_shift_by_row, info.format.pixel_shift_by_row)
    np.testing.assert_array_equal(meta.beam_altitude_angles, info.beam_altitude_angles)
    np.testing.assert_array_equal(meta.beam_azimuth_angles, info.beam_azimuth_angles)
    np.testing.assert_array_equal(meta.beam_to_lidar_transform, info.beam_to_lidar_transform)
    np.testing.assert_array_equal(meta.lidar_to_sensor_transform, info.lidar_to_sensor_transform)
    assert meta.lidar_origin_to_beam_origin_mm == info.lidar_origin_to_beam_origin_mm
    if info.format.udp_profile_lidar.name != "OFF":  # the SDK turns lidar off when its UDP port is 0
        assert meta.udp_profile_lidar == info.format.udp_profile_lidar.name
        assert packet_layout(meta).packet_size == sdk.PacketFormat(info).lidar_packet_size


def test_metadata_errors_name_the_key():
    doc = json.loads((DATA / "OS-2-128-U1_v2.3.0_1024x10.json").read_text())
    del doc["data_format"]["pixels_per_column"]
    with pytest.raises(ValueError, match="pixels_per_column"):
        parse_metadata(doc)
    doc = json.loads((DATA / "OS-2-128-U1_v2.3.0_1024x10.json").read_text())
    doc["data_format"]["udp_profile_lidar"] = "NO_SUCH_PROFILE"
    with pytest.raises(ValueError, match="NO_SUCH_PROFILE"):
        packet_layout(parse_metadata(doc))


@pytest.mark.parametrize("columns", [1024, 2048])
def test_simulated_os128_metadata_is_accepted_by_sdk(columns):
    meta = simulated_os128_metadata(columns)
    text = metadata_to_json(meta)
    info = sdk.SensorInfo(text)
    assert (info.w, info.h, info.format.udp_profile_lidar.name) == (columns, 128, "LEGACY")
    assert sdk.PacketFormat(info).lidar_packet_size == packet_layout(meta).packet_size == 24896
    assert packet_layout(meta).packets_per_frame == columns // 16
    again = parse_metadata(text)
    for name in ("lidar_mode", "init_id", "prod_sn", "udp_profile_lidar", "column_window"):
        assert getattr(again, name) == getattr(meta, name)
    for name in ("pixel_shift_by_row", "beam_altitude_angles", "beam_to_lidar_transform"):
        np.testing.assert_array_equal(getattr(again, name), getattr(meta, name))


# ---------------------------------------------------------------- real captures against the SDK


@pytest.mark.parametrize("stem", sorted(CAPTURES))
def test_capture_packets_decode_like_sdk(stem):
    text, meta, layout = _load(stem)
    info = sdk.SensorInfo(text)
    fmt = sdk.PacketFormat(info)
    payloads = _capture_payloads(CAPTURES[stem])
    batch = decode_packets(payloads, layout, prod_sn=int(meta.prod_sn))
    assert batch.counts.packets_decoded == batch.counts.packets_in == len(payloads)
    assert batch.counts.invalid_columns == 0
    for p, payload in enumerate(payloads):
        buf = np.frombuffer(payload, np.uint8)
        assert batch.frame_id[p] == fmt.frame_id(buf)
        np.testing.assert_array_equal(batch.column_index[p], fmt.packet_header(sdk.ColHeader.MEASUREMENT_ID, buf))
        np.testing.assert_array_equal(batch.timestamp_ns[p], fmt.packet_header(sdk.ColHeader.TIMESTAMP, buf))
        for name, sdk_name in SDK_FIELDS.items():
            mine = getattr(batch, name)
            assert (mine is None) == (sdk_name not in list(fmt.fields)), name
            if mine is not None:
                np.testing.assert_array_equal(mine[p], fmt.packet_field(sdk_name, buf).T, err_msg=name)
    assert count_missing_packets(packet_sequence(batch, layout), layout) == 0


@pytest.mark.parametrize("stem", sorted(CAPTURES))
def test_capture_scans_and_points_match_sdk(stem):
    text, meta, layout = _load(stem)
    info = sdk.SensorInfo(text)
    payloads = _capture_payloads(CAPTURES[stem])
    batch = decode_packets(payloads, layout)
    assembler = ouster_scan_assembler(layout)
    scans = assembler.add(batch) + assembler.flush()
    frames = _sdk_frames(info, payloads)
    assert [s.frame_id for s in scans] == [f.frame_id for f in frames]
    lut = make_xyz_lut(meta)
    sdk_lut = sdk.XYZLut(info)
    for scan, frame in zip(scans, frames, strict=True):
        assert scan.packets_received == int(np.count_nonzero(frame.packet_timestamp))
        np.testing.assert_array_equal(scan.column_valid, (frame.status & 1) == 1)
        np.testing.assert_array_equal(scan.timestamp_ns, frame.timestamp)
        for name in ("range_mm", "reflectivity", "signal", "near_ir", "range2_mm"):
            mine = getattr(scan, name)
            if mine is not None:
                np.testing.assert_array_equal(mine, frame.field(SDK_FIELDS[name]), err_msg=name)
        cloud = scan_point_cloud(scan, lut)
        sdk_xyz = sdk_lut(frame)
        assert len(cloud.xyz) == np.count_nonzero(frame.field("RANGE")) > 1000
        np.testing.assert_allclose(cloud.xyz, sdk_xyz[cloud.ring, cloud.column], **XYZ)
        np.testing.assert_array_equal(cloud.range_mm, frame.field("RANGE")[cloud.ring, cloud.column])
        np.testing.assert_array_equal(cloud.timestamp_ns, frame.timestamp[cloud.column])
        np.testing.assert_array_equal(
            destagger(scan.range_mm, meta.pixel_shift_by_row), sdk.destagger(info, frame.field("RANGE"))
        )

    # every pixel of every packet, zero range included, straight from the batch
    xyz = batch_xyz(batch, lut)
    for p in range(batch.num_packets):
        image = np.zeros((meta.pixels_per_column, meta.columns_per_frame), np.uint32)
        image[:, batch.column_index[p]] = batch.range_mm[p].T
        expected = sdk_lut(image)[:, batch.column_index[p]].transpose(1, 0, 2)
        np.testing.assert_allclose(xyz[p], expected, **XYZ)
    if batch.range2_mm is not None:
        xyz2 = batch_xyz(batch, lut, batch.range2_mm)
        assert np.count_nonzero(xyz2.any(axis=-1)) == np.count_nonzero(batch.range2_mm)


def test_xyz_lut_with_sensor_to_body_matches_sdk_extrinsics():
    text, meta, _ = _load("OS-2-128-U1_v2.3.0_1024x10")
    info = sdk.SensorInfo(text)
    sensor_to_body = np.eye(4)
    sensor_to_body[:2, :2] = [[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]
    sensor_to_body[:3, 3] = [1.5, -0.2, 1.9]
    info.sensor_to_body = sensor_to_body
    ranges = np.random.default_rng(0).integers(0, 200_000, (128, 1024)).astype(np.uint32)
    lut = make_xyz_lut(meta, sensor_to_body)
    ours = (lut.direction_image * ranges + lut.offset_image) * (ranges != 0)
    np.testing.assert_allclose(np.moveaxis(ours, 0, -1), sdk.XYZLut(info, use_extrinsics=True)(ranges), **XYZ)


def test_os0_128_scan_matches_ousters_own_digest():
    """Ouster's expected-output digest for this capture: md5 of the SDK's frame fields."""
    _, _, layout = _load("OS-0-128-U1_v2.3.0_1024x10")
    digest = json.loads((DATA / "OS-0-128-U1_v2.3.0_1024x10_digest.json").read_text())["scans"][0]
    batch = decode_packets(_capture_payloads("OS-0-128-U1_v2.3.0_1024x10"), layout)
    (scan,) = ouster_scan_assembler(layout).add(batch)
    assert scan.complete and scan.frame_id == int(digest["FRAME_ID"])

    def md5(a: np.ndarray) -> str:
        return hashlib.md5(np.ascontiguousarray(a).tobytes()).hexdigest()

    assert md5(scan.range_mm) == digest["RANGE"]
    assert md5(scan.reflectivity) == digest["REFLECTIVITY"]
    assert md5(scan.near_ir) == digest["NEAR_IR"]
    assert md5(scan.timestamp_ns) == digest["TIMESTAMP"]
    assert md5(batch.column_index.ravel().astype(np.uint16)) == digest["MEASUREMENT_ID"]


def test_imu_and_zone_datagrams_are_counted_as_wrong_size():
    _, _, layout = _load("OS-2-128-U1_v2.3.0_1024x10")
    everything = _capture_payloads("OS-2-128-U1_v2.3.0_1024x10", port=None)
    counts = decode_packets(everything, layout).counts
    assert (counts.packets_decoded, counts.wrong_size) == (64, 10)
    _, _, zone_layout = _load("imu_zm_no_lidar_0")
    imu_only = _capture_payloads("imu_zm_no_lidar", port=None)
    counts = decode_packets(imu_only, zone_layout).counts
    assert (counts.packets_in, counts.wrong_size, counts.packets_decoded) == (9, 9, 0)


# ---------------------------------------------------------------- encoder round trips


def _synthetic_frame(layout, seed: int = 1):
    rng = np.random.default_rng(seed)
    h, w = layout.pixels_per_column, layout.columns_per_frame
    pixels = {}
    for name, field in layout.pixel_fields.items():
        values = rng.integers(0, 1 << (field.bits + field.upshift), (h, w))
        values[rng.random((h, w)) < 0.1] = 0  # some pixels without a return
        pixels[name] = values >> field.upshift << field.upshift  # what the profile can carry
    timestamps = 1_700_000_000_000_000_000 + np.arange(w, dtype=np.uint64) * np.uint64(100_000_000 // w)
    valid = np.ones(w, bool)
    valid[[3, 17, w - 1]] = False
    return pixels, timestamps, valid


@pytest.mark.parametrize("profile", sorted(PROFILE_PIXEL_FIELDS))
@pytest.mark.parametrize("columns", [1024, 2048])
def test_encoded_frame_decodes_to_input_in_sdk_and_here(profile, columns):
    meta = simulated_os128_metadata(columns, udp_profile_lidar=profile)
    layout = packet_layout(meta)
    info = sdk.SensorInfo(metadata_to_json(meta))
    pixels, timestamps, valid = _synthetic_frame(layout)
    packets = encode_frame_packets(
        layout, 4242, pixels, timestamps, valid, init_id=meta.init_id, prod_sn=int(meta.prod_sn)
    )
    assert packets.shape == (columns // 16, sdk.PacketFormat(info).lidar_packet_size)
    if profile == "LEGACY":
        assert packets.shape[1] == 24896

    (frame,) = _sdk_frames(info, [bytes(row) for row in packets])
    batch = decode_packets(packets, layout, prod_sn=int(meta.prod_sn))
    (scan,) = ouster_scan_assembler(layout).add(batch)
    assert frame.frame_id == scan.frame_id == 4242 and scan.complete
    assert batch.counts.invalid_columns == 3
    np.testing.assert_array_equal(frame.timestamp[valid], timestamps[valid])
    np.testing.assert_array_equal(scan.timestamp_ns[valid], timestamps[valid])
    for name, values in pixels.items():
        expected = np.where(valid, values, 0)
        np.testing.assert_array_equal(frame.field(SDK_FIELDS[name]), expected, err_msg=name)
        np.testing.assert_array_equal(
            np.moveaxis(getattr(batch, name), 2, 0).reshape(expected.shape[0], -1)[:, valid], values[:, valid]
        )
    cloud = scan_point_cloud(scan, make_xyz_lut(meta))
    expected_xyz = sdk.XYZLut(info)(np.where(valid, pixels["range_mm"], 0).astype(np.uint32))
    np.testing.assert_allclose(cloud.xyz, expected_xyz[cloud.ring, cloud.column], **XYZ)
    assert len(cloud.xyz) == np.count_nonzero(np.where(valid, pixels["range_mm"], 0))


@pytest.mark.parametrize("profile", sorted(PROFILE_PIXEL_FIELDS))
def test_a_renumbered_packet_is_the_one_the_sensor_would_send_frames_later(profile):
    meta = simulated_os128_metadata(1024, udp_profile_lidar=profile)
    layout = packet_layout(meta)
    pixels, timestamps, valid = _synthetic_frame(layout)
    frame_id, later = layout.frame_id_modulus - 2, 5  # the frame id wraps
    packets = encode_frame_packets(layout, frame_id, pixels, timestamps, valid, init_id=meta.init_id,
                                   prod_sn=int(meta.prod_sn))
    expected = encode_frame_packets(layout, frame_id + later, pixels, timestamps + np.uint64(8_000_000_000), valid,
                                    init_id=meta.init_id, prod_sn=int(meta.prod_sn))
    for packet, want in zip(packets, expected, strict=True):
        assert packet_frame_id(bytes(packet), layout) == frame_id
        moved = renumbered_packet(bytes(packet), layout, later, 8_000_000_000)
        assert moved == bytes(want) and packet_frame_id(moved, layout) == 3


def test_encoder_matches_sdk_frame_to_packets_byte_for_byte_on_pixels():
    """The SDK's own encoder and ours give the same pixel bytes for the same LEGACY frame."""
    meta = simulated_os128_metadata(2048)
    layout = packet_layout(meta)
    info = sdk.SensorInfo(metadata_to_json(meta))
    pixels, timestamps, _ = _synthetic_frame(layout, seed=7)
    frame = sdk.LidarFrame(info)
    for name, values in pixels.items():
        frame.field(SDK_FIELDS[name])[:] = values
    frame.timestamp[:] = timestamps
    frame.measurement_id[:] = np.arange(2048)
    frame.status[:] = 0xFFFFFFFF
    frame.frame_id = 9
    theirs = [np.asarray(p.buf) for p in sdk.frame_to_packets(frame, sdk.PacketFormat(info), meta.init_id, 0)]
    ours = encode_frame_packets(layout, 9, pixels, timestamps)
    assert len(theirs) == len(ours)
    col = layout.column_size
    for a, b in zip(theirs, ours, strict=True):
        a, b = a.reshape(16, col), b.reshape(16, col)
        np.testing.assert_array_equal(a[:, :10], b[:, :10])  # time stamp, measurement id
        # the SDK writes the frame id into the first column only; a sensor writes it in every column
        np.testing.assert_array_equal(a[0, 10:12], b[0, 10:12])
        assert np.all(b[:, 10:12] == b[0, 10:12])
        np.testing.assert_array_equal(a[:, 16:], b[:, 16:])  # pixels and status


# ---------------------------------------------------------------- malformed input and packet loss


def test_malformed_datagrams_are_counted_and_skipped():
    text, meta, layout = _load("OS-2-128-U1_v2.3.0_1024x10")
    good = _capture_payloads("OS-2-128-U1_v2.3.0_1024x10")
    clean = decode_packets(good, layout, prod_sn=int(meta.prod_sn))
    rng = np.random.default_rng(3)

    def patched(i: int, offset: int, value: bytes) -> bytes:
        b = bytearray(good[i])
        b[offset : offset + len(value)] = value
        return bytes(b)

    col0 = 32  # first column header in a non-legacy packet
    bad_size = [good[0][:100], good[1][:-1], good[2] + b"\0", b"", rng.bytes(70000)]
    bad_header = [
        patched(3, 0, b"\x02\x00"),  # packet type: not lidar
        patched(4, 7, b"\x01\x02\x03\x04\x05"),  # another sensor's serial number
        patched(5, col0 + 8, struct.pack("<H", 1020)),  # measurement ids run past the frame
        patched(6, col0 + layout.column_size * 3 + 8, struct.pack("<H", 999)),  # out of sequence
        rng.bytes(layout.packet_size),  # garbage of the right size
    ]
    invalid_column = patched(7, col0 + layout.column_size * 2 + 10, b"\x00\x00")
    stream = bad_size + bad_header + [invalid_column] + good[8:]
    batch = decode_packets(stream, layout, prod_sn=int(meta.prod_sn))
    c = batch.counts
    assert (c.packets_in, c.wrong_size, c.bad_header) == (len(stream), 5, 5)
    assert (c.packets_decoded, c.invalid_columns) == (1 + len(good) - 8, 1)
    np.testing.assert_array_equal(batch.packet_index, np.arange(10, len(stream)))
    assert not batch.column_valid[0, 2] and batch.column_valid[0].sum() == 15
    np.testing.assert_array_equal(batch.range_mm[1:], clean.range_mm[8:])
    # the invalid column is left empty in the scan, the rest is there
    assembler = ouster_scan_assembler(layout)
    scan = (assembler.add(batch) + assembler.flush())[0]
    assert not scan.column_valid[7 * 16 + 2] and scan.column_valid.sum() == (len(good) - 7) * 16 - 1
    assert count_missing_packets(packet_sequence(batch, layout), layout) == 0  # 0..6 lost before the first

    # an (N, S) receive buffer with lengths, as a socket driver fills it
    buffer = np.zeros((4, 65536), np.uint8)
    for i in range(4):
        buffer[i, : len(good[i])] = np.frombuffer(good[i], np.uint8)
    sized = decode_packets(buffer, layout, sizes=np.array([len(good[0]), 12, len(good[2]), 0]))
    assert (sized.counts.packets_decoded, sized.counts.wrong_size) == (2, 2)
    np.testing.assert_array_equal(sized.range_mm, clean.range_mm[[0, 2]])


def test_legacy_frame_id_disagreement_is_a_bad_header():
    meta = simulated_os128_metadata(1024)
    layout = packet_layout(meta)
    pixels, timestamps, _ = _synthetic_frame(layout)
    packets = encode_frame_packets(layout, 5, pixels, timestamps)
    packets[1, layout.column_size * 5 + 10] ^= 1  # one column claims another frame
    batch = decode_packets(packets, layout)
    assert (batch.counts.bad_header, batch.counts.packets_decoded) == (1, 63)


def _stream(layout, frame_ids: list[int]) -> np.ndarray:
    pixels, timestamps, _ = _synthetic_frame(layout)
    return np.concatenate([encode_frame_packets(layout, f, pixels, timestamps) for f in frame_ids])


@pytest.mark.parametrize("profile", ["LEGACY", "FUSA_RNG15_RFL8_NIR8_DUAL"])
def test_dropped_packets_are_counted_exactly(profile):
    meta = simulated_os128_metadata(1024, udp_profile_lidar=profile)
    layout = packet_layout(meta)
    last = layout.frame_id_modulus - 1
    packets = _stream(layout, [last - 1, last, 0, 1])  # frame id wraps
    rng = np.random.default_rng(11)
    for trial in range(20):
        n_drop = [0, 1, 5, 64, 100][trial % 5]
        dropped = rng.choice(np.arange(1, len(packets) - 1), n_drop, replace=False)
        kept = np.delete(packets, dropped, axis=0)
        batch = decode_packets(kept, layout)
        sequence = packet_sequence(batch, layout)
        assert count_missing_packets(sequence, layout) == n_drop
        # split into two batches, carrying the newest sequence number across
        split = len(sequence) // 3
        first, second = batch.select(slice(0, split)), batch.select(slice(split, None))
        first_sequence = packet_sequence(first, layout)
        newest = newest_packet(first_sequence, layout)
        missing_second = count_missing_packets(packet_sequence(second, layout), layout, previous=newest)
        assert count_missing_packets(first_sequence, layout) + missing_second == n_drop
    # reordered or repeated packets are not losses, also across batches
    batch = decode_packets(packets[[0, 1, 3, 2, 4, 4, 5, 7, 6, 8, 10]], layout)
    sequence = packet_sequence(batch, layout)
    assert count_missing_packets(sequence, layout) == 1  # packet 9
    assert newest_packet(sequence[:8], layout) == sequence[7]
    assert count_missing_packets(sequence[8:], layout, previous=newest_packet(sequence[:8], layout)) == 1
    # the newest packet is found across the frame id wrap
    wrapped = packet_sequence(decode_packets(packets[[60, 130, 70]], layout), layout)
    assert newest_packet(wrapped, layout) == wrapped[1]
    assert count_missing_packets(wrapped, layout) == 130 - 60 + 1 - 3


def test_dropped_packets_in_real_capture():
    _, _, layout = _load("OS-1-128_v2.3.0_1024x10")
    payloads = _capture_payloads("OS-1-128_v2.3.0_1024x10_lb_n3")
    dropped = {5, 63, 64, 65, 120, 190}
    kept = [p for i, p in enumerate(payloads) if i not in dropped]
    batch = decode_packets(kept, layout)
    assert count_missing_packets(packet_sequence(batch, layout), layout) == len(dropped)
    assembler = ouster_scan_assembler(layout)
    scans = assembler.add(batch) + assembler.flush()
    assert [s.packets_received for s in scans] == [64 - 2, 64 - 3, 64 - 1]
    assert not any(s.complete for s in scans)


# ---------------------------------------------------------------- scan assembly


def test_scan_assembler_releases_complete_incomplete_and_late_scans():
    meta = simulated_os128_metadata(1024)
    layout = packet_layout(meta)
    packets = _stream(layout, [10, 11, 12])
    assembler = ouster_scan_assembler(layout)
    first = assembler.add(decode_packets(packets[:64], layout))
    assert [(s.frame_id, s.complete) for s in first] == [(10, True)]  # released without waiting
    partial = packets[64:100]
    assert assembler.add(decode_packets(partial, layout)) == []
    late = assembler.add(decode_packets(packets[:3], layout))  # frame 10 again
    assert late == [] and assembler.late_packets == 3
    second = assembler.add(decode_packets(packets[128:130], layout))
    assert [(s.frame_id, s.packets_received) for s in second] == [(11, 36)]
    assert assembler.add(decode_packets(packets[100:101], layout)) == [] and assembler.late_packets == 4
    assembler.add(decode_packets(packets[129:130], layout))
    assert assembler.duplicate_packets == 1
    assert [(s.frame_id, s.packets_received) for s in assembler.flush()] == [(12, 2)]
    assert assembler.flush() == []


def test_destagger_inverts_and_matches_sdk():
    _, meta, _ = _load("OS-1-128_767798045_1024x10_20230712_120049")  # negative pixel shifts
    image = np.arange(128 * 1024, dtype=np.uint32).reshape(128, 1024)
    staggered = destagger(image, meta.pixel_shift_by_row)
    np.testing.assert_array_equal(staggered, sdk.destagger(image, list(meta.pixel_shift_by_row)))
    np.testing.assert_array_equal(destagger(staggered, meta.pixel_shift_by_row, inverse=True), image)


# ---------------------------------------------------------------- real UDP socket and pcap framing


def test_packets_through_a_udp_socket_decode_from_a_receive_buffer():
    meta = simulated_os128_metadata(1024)
    layout = packet_layout(meta)
    packets = _stream(layout, [1])
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    receiver.bind(("127.0.0.1", 0))
    receiver.settimeout(2.0)
    buffer = np.zeros((len(packets), 65536), np.uint8)
    sizes = np.zeros(len(packets), np.int64)
    try:
        for i, packet in enumerate(packets):
            sender.sendto(packet.tobytes(), receiver.getsockname())
            sizes[i] = receiver.recv_into(memoryview(buffer[i]))
    finally:
        sender.close()
        receiver.close()
    batch = decode_packets(buffer, layout, sizes=sizes)
    assert batch.counts.packets_decoded == 64
    (scan,) = ouster_scan_assembler(layout).add(batch)
    pixels, _, _ = _synthetic_frame(layout)
    np.testing.assert_array_equal(scan.range_mm, pixels["range_mm"])


def _pcap_record(frame: bytes, t_ns: int) -> bytes:
    return struct.pack("<IIII", t_ns // 10**9, t_ns % 10**9 // 1000, len(frame), len(frame)) + frame


def _ipv4_udp(payload: bytes, dport: int, fragment: bool = False, vlan: bool = False) -> bytes:
    udp = struct.pack(">HHHH", 7502, dport, 8 + len(payload), 0) + payload
    ip = struct.pack(
        ">BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0x2000 if fragment else 0, 64, 17, 0, bytes(4), bytes(4)
    )
    eth_type = b"\x81\x00\x00\x05\x08\x00" if vlan else b"\x08\x00"
    return bytes(12) + eth_type + ip + udp


def test_pcap_reader_frames_udp_by_hand(tmp_path):
    path = tmp_path / "t.pcap"
    header = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)
    records = [
        _pcap_record(_ipv4_udp(b"lidar", 7502), 1_500_000_000_000_001_000),
        _pcap_record(_ipv4_udp(b"tagged", 7502, vlan=True), 1_500_000_000_000_002_000),
        _pcap_record(_ipv4_udp(b"imu", 7503), 1_500_000_000_000_003_000),
        _pcap_record(_ipv4_udp(b"part", 7502, fragment=True), 1_500_000_000_000_004_000),
        _pcap_record(bytes(12) + b"\x08\x06" + bytes(28), 1_500_000_000_000_005_000),  # ARP
    ]
    path.write_bytes(header + b"".join(records) + b"\x00\x01")
    capture = read_pcap_udp(path, dst_port=7502)
    assert [d.payload for d in capture.datagrams] == [b"lidar", b"tagged"]
    assert capture.datagrams[0].timestamp_ns == 1_500_000_000_000_001_000
    assert (capture.skipped_fragments, capture.skipped_not_udp, capture.skipped_truncated) == (1, 1, 1)
    assert len(read_pcap_udp(path).datagrams) == 3


# ---------------------------------------------------------------- fuzzing

_FUZZ_LAYOUTS = {
    stem: _load(stem)[2] for stem in ("OS-2-128-U1_v2.3.0_1024x10", "OS-1-128_767798045_1024x10_20230712_120049")
}
_FUZZ_LAYOUTS["LEGACY"] = packet_layout(simulated_os128_metadata(1024))
_REAL = {stem: _capture_payloads(CAPTURES[stem])[:8] for stem in _FUZZ_LAYOUTS if stem in CAPTURES}
_REAL["LEGACY"] = [bytes(p) for p in _stream(_FUZZ_LAYOUTS["LEGACY"], [3])[:8]]


def _check_batch(batch: LidarPacketBatch, layout, n_in: int) -> None:
    c = batch.counts
    assert c.packets_in == n_in == c.packets_decoded + c.wrong_size + c.bad_header
    assert batch.num_packets == c.packets_decoded
    assert c.invalid_columns == np.count_nonzero(~batch.column_valid)
    assert np.all((batch.column_index >= 0) & (batch.column_index < layout.columns_per_frame))
    assembler = ouster_scan_assembler(layout)
    assembler.add(batch)
    assembler.flush()
    count_missing_packets(packet_sequence(batch, layout), layout)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    stem=st.sampled_from(sorted(_FUZZ_LAYOUTS)),
    data=st.data(),
)
def test_fuzz_random_datagrams_never_raise(stem, data):
    layout = _FUZZ_LAYOUTS[stem]
    sizes = st.one_of(st.integers(0, 64), st.just(layout.packet_size), st.integers(0, 65507))
    lengths = data.draw(st.lists(sizes, max_size=6))
    datagrams = [
        data.draw(st.binary(min_size=n, max_size=n)) if n < 200 else np.random.default_rng(n).bytes(n) for n in lengths
    ]
    _check_batch(decode_packets(datagrams, layout), layout, len(datagrams))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(stem=st.sampled_from(sorted(_REAL)), data=st.data())
def test_fuzz_mutated_real_packets_never_raise(stem, data):
    layout = _FUZZ_LAYOUTS[stem]
    datagrams = []
    for packet in _REAL[stem]:
        b = bytearray(packet)
        for _ in range(data.draw(st.integers(0, 4))):
            where = data.draw(st.integers(0, len(b) - 1))
            b[where] = data.draw(st.integers(0, 255))
        if data.draw(st.booleans()):
            b = b[: data.draw(st.integers(0, len(b)))]
        datagrams.append(bytes(b))
    batch = decode_packets(datagrams, layout)
    _check_batch(batch, layout, len(datagrams))
    assert batch.counts.wrong_size == sum(len(d) != layout.packet_size for d in datagrams)
