"""The `vendors` figures of bench/lidar.py: per Lidar model beyond Ouster, our decoder's points/s on one
core on the shared real captures, its largest xyz difference from the model's reference decoder, and
the reference's own points/s measured side by side (Velodyne: velodyne-decoder 3.1.0, C++). Hesai has no
reference decoder to run here: the error is against tier4/nebula's reference cloud of one rotation, and the
Pandar128E4X and AT128 (no capture) are timed on self-made packets, without an error figure."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the Hesai figures use the test-side packet encoders (tests/drivers/)

from drivers.lidar.hesai_decoder import hesai_decoder  # noqa: E402
from drivers.lidar.packet_decoding import rotation_starts  # noqa: E402
from drivers.lidar.pcap_udp import read_pcap_udp  # noqa: E402
from drivers.lidar.velodyne_calibration import load_velodyne_calibration  # noqa: E402
from drivers.lidar.velodyne_decoder import VelodyneDecoder  # noqa: E402

NEBULA = Path("/work/shared/data/lidar_nebula")
HESAI_CAPTURES = {  # model: (capture, angle table, the reference cloud's minimum range)
    "hesai-pandar40p": ("40p", "Pandar40P", 0.3),
    "hesai-pandar64": ("64", "Pandar64", 0.3),
    "hesai-pandarqt128": ("qt128", "PandarQT128", 0.3),
    "hesai-pandarxt32": ("xt32", "PandarXT32", 0.05),
}
VELODYNE_CAPTURES = {"VLP-16": ("vlp16", "VLP16"), "VLP-32C": ("vlp32", "VLP32"), "VLS-128": ("vls128", "VLS128")}


def _velodyne_decoder_run(calibration_path: Path, payloads: list[tuple[float, bytes]]) -> Callable[[], np.ndarray]:
    import velodyne_decoder as vd

    config = vd.Config()
    config.calibration = vd.Calibration.read(str(calibration_path))

    def run() -> np.ndarray:
        decoder = vd.StreamDecoder(config)
        scans = [r[1] for stamp, p in payloads if (r := decoder.decode(stamp, p)) is not None]
        if (r := decoder.finish()) is not None:
            scans.append(r[1])
        return np.concatenate(scans)

    return run


def velodyne_figures(time_medians: Callable[[list, int], tuple[list[float], list[float]]], repeats: int) -> dict:
    """{model: figures} for each shared Velodyne capture; CPU seconds of this thread, median of `repeats`."""
    figures = {}
    for model, (capture, calibration_name) in VELODYNE_CAPTURES.items():
        calibration_path = NEBULA / "calib" / f"{calibration_name}.yaml"
        datagrams = read_pcap_udp(NEBULA / "velodyne" / f"{capture}.pcap").datagrams
        payloads = [d.payload for d in datagrams]
        calibration = load_velodyne_calibration(calibration_path)
        reference_run = _velodyne_decoder_run(calibration_path, [(d.timestamp_ns * 1e-9, d.payload) for d in datagrams])

        def ours_run(payloads=payloads, calibration=calibration):
            return VelodyneDecoder(calibration).decode(payloads)

        ours, reference = ours_run(), reference_run()
        if len(ours.xyz) != len(reference):
            raise AssertionError(f"{model}: {len(ours.xyz)} points, velodyne-decoder {len(reference)}")
        (t_ours, t_reference), _ = time_medians([ours_run, reference_run], repeats)
        figures[model] = {
            "points_per_s": round(len(ours.xyz) / t_ours),
            "max_abs_err_m": float(np.abs(ours.xyz - reference[:, :3]).max()),
            "reference": "velodyne-decoder 3.1.0",
            "reference_points_per_s": round(len(reference) / t_reference),
            "reference_ratio": round(t_reference / t_ours, 3),
            "points": len(ours.xyz),
            "packets": len(payloads),
        }
    return figures


def _nebula_reference_error(points, check, capture: str) -> tuple[float, float, int, int]:
    """(max, median) distance from each point of nebula's reference cloud (its x right, y forward) to our
    nearest point of the rotation it is (the one ours reproduce best; widened by 5 % of its packets each side
    since nebula cuts at the points' corrected azimuth), that rotation's size, and the reference's."""
    from scipy.spatial import cKDTree

    from tests.drivers.hesai_test_packets import read_binary_pcd

    ref = read_binary_pcd(NEBULA / "hesai" / f"{capture}.reference.pcd")
    ref = np.stack([ref[:, 1], -ref[:, 0], ref[:, 2]], axis=1)
    cuts = np.concatenate([[0], rotation_starts(check.azimuth_cdeg), [len(check.accepted)]])
    best = None
    for start, end in zip(cuts[:-1], cuts[1:], strict=True):
        pad = (end - start) // 20
        near = (points.packet_index >= start - pad) & (points.packet_index < end + pad)
        distance, _ = cKDTree(points.xyz[near]).query(ref)
        size = int(((points.packet_index >= start) & (points.packet_index < end)).sum())
        if best is None or np.mean(distance < 1e-4) > best[0]:
            best = (np.mean(distance < 1e-4), float(distance.max()), float(np.median(distance)), size)
    return best[1], best[2], best[3], len(ref)


def _self_made_packets(model: str, n_packets: int = 2000) -> list[bytes]:
    """Pandar128E4X / AT128 single-return packets of random ranges (2-160 m, 10 % without return) over turns."""
    from tests.drivers.hesai_test_packets import encode_128e4x, encode_at128

    rng = np.random.default_rng(0)
    packets = []
    for i in range(n_packets):
        distance = rng.integers(500, 40_000, (2, 128))
        distance[rng.random((2, 128)) < 0.1] = 0
        reflectivity = rng.integers(0, 256, (2, 128))
        if model == "hesai-pandar128e4x":
            azimuth = (i * 20 % 36000, (i * 20 + 10) % 36000)
            packets.append(encode_128e4x(azimuth, distance, reflectivity, 1_700_000_000, i * 56 % 1_000_000))
        else:
            motor = (i * 2560 % (360 * 25600), (i * 2560 + 1280) % (360 * 25600))
            packets.append(encode_at128(motor, distance, reflectivity, 1_700_000_000, i * 83 % 1_000_000))
    return packets


def hesai_figures(time_medians: Callable[[list, int], tuple[list[float], list[float]]], repeats: int) -> dict:
    """{model: figures} for each Hesai model: the four shared captures against nebula's reference clouds; the
    128E4X and AT128 on self-made packets (the AT128 with a self-made correction file from its angle CSV)."""
    import shutil
    import tempfile

    from tests.drivers.hesai_test_packets import at128_correction_from_table

    at128_correction = Path(tempfile.mkdtemp()) / "PandarAT128.dat"
    at128_correction.write_bytes(at128_correction_from_table(NEBULA / "calib" / "PandarAT128.csv"))
    figures = {}
    runs = {}
    for model, (capture, table, min_range) in HESAI_CAPTURES.items():
        payloads = [d.payload for d in read_pcap_udp(NEBULA / "hesai" / f"{capture}.pcap").datagrams]
        decoder = hesai_decoder(model, NEBULA / "calib" / f"{table}.csv", min_range_m=min_range)
        points = decoder.decode(payloads)
        max_err, median_err, size, reference_size = _nebula_reference_error(points, decoder.check(payloads), capture)
        figures[model] = {
            "max_abs_err_m": max_err, "median_err_m": median_err,
            "reference": "tier4/nebula reference cloud of one rotation (nearest point)",
            "points_per_rotation": size, "reference_points": reference_size,
            "points": len(points.xyz), "packets": len(payloads),
        }
        runs[model] = (decoder, payloads, len(points.xyz))
    for model, table in (("hesai-pandar128e4x", NEBULA / "calib" / "Pandar128E4X.csv"),
                         ("hesai-pandarat128", at128_correction)):
        decoder = hesai_decoder(model, table)
        payloads = _self_made_packets(model)
        n_points = len(decoder.decode(payloads).xyz)
        figures[model] = {"max_abs_err_m": None, "reference": "none: self-made packets, single return",
                          "points": n_points, "packets": len(payloads)}
        runs[model] = (decoder, payloads, n_points)
    shutil.rmtree(at128_correction.parent)  # the decoder has read it
    cpu, _ = time_medians([lambda d=d, p=p: d.decode(p) for d, p, _ in runs.values()], repeats)
    for (model, (_, _, n_points)), t in zip(runs.items(), cpu, strict=True):
        figures[model] = {"points_per_s": round(n_points / t)} | figures[model]
    return figures


def _tests_importable() -> None:
    """The synthetic packets come from the test-side encoders under tests/drivers: the repository root on
    the import path, as the other benches put it."""
    import sys

    root = str(Path(__file__).resolve().parents[1])
    if root not in sys.path:
        sys.path.insert(0, root)


def hdl64e_figures(time_medians: Callable[[list, int], tuple[list[float], list[float]]], repeats: int) -> dict:
    """{"HDL-64E S3": figures}: no HDL-64E capture is shared, so on 1,000 packets the test-side encoder makes
    (labelled synthetic), with the real S3 calibration in tests/data/velodyne, all its corrections."""
    import velodyne_decoder as vd

    _tests_importable()
    from tests.drivers.test_velodyne_hdl64e import CALIBRATION, encode_hdl64e

    payloads = encode_hdl64e(1000, dual=False)
    calibration = load_velodyne_calibration(CALIBRATION)
    config = vd.Config(model=vd.Model.HDL64E_S3, calibration=vd.Calibration.read(str(CALIBRATION)))

    def ours_run():  # a new decoder each run, the file read once, as in velodyne_figures
        return VelodyneDecoder(calibration, hdl64e="HDL-64E S3").decode(payloads)

    def reference_run() -> np.ndarray:
        decoder = vd.StreamDecoder(config)
        scans = [r[1] for i, p in enumerate(payloads) if (r := decoder.decode(i * 288e-6, p)) is not None]
        if (r := decoder.finish()) is not None:
            scans.append(r[1])
        return np.concatenate(scans)

    ours, reference = ours_run(), reference_run()
    if len(ours.xyz) != len(reference):
        raise AssertionError(f"HDL-64E: {len(ours.xyz)} points, velodyne-decoder {len(reference)}")
    (t_ours, t_reference), _ = time_medians([ours_run, reference_run], repeats)
    return {
        "HDL-64E S3": {
            "points_per_s": round(len(ours.xyz) / t_ours),
            "max_abs_err_m": float(np.abs(ours.xyz - reference[:, :3]).max()),
            "reference": "velodyne-decoder 3.1.0",
            "reference_points_per_s": round(len(reference) / t_reference),
            "reference_ratio": round(t_reference / t_ours, 3),
            "points": len(ours.xyz),
            "packets": len(payloads),
            "synthetic": True,
        }
    }


def robosense_figures(time_medians: Callable[[list, int], tuple[list[float], list[float]]], repeats: int,
                      quick: bool) -> dict:
    """{model: figures} for RoboSense: our decoder's points/s on one core (CPU seconds of this thread,
    median of `repeats`) and its largest xyz difference from the reference. Helios-16P: the shared real capture,
    against Nebula's decoded cloud of its first rotation (no Python decoder exists to time beside it).
    Ruby-128: packets from the test-side encoder (synthetic), against the float64 geometry that test computes."""
    from drivers.lidar.robosense_decoder import robosense_decoder

    figures = {}
    payloads = [d.payload for d in read_pcap_udp(NEBULA / "robosense" / "helios16P.pcap").datagrams]
    decoder = robosense_decoder("robosense-helios16p", NEBULA / "calib" / "RobosenseHelios16P.csv")
    points = decoder.decode(payloads)
    reference = np.loadtxt(NEBULA / "robosense" / "helios16P.reference.pcd", skiprows=11)
    error = np.abs(points.xyz[: len(reference)].astype(np.float64) - reference[:, :3]).max(axis=1)
    figures["Helios-16P"] = {
        "max_abs_err_m": float(error.max()),
        "p99_abs_err_m": float(np.quantile(error, 0.99)),
        "reference": "Nebula's decoded first rotation (point by point)",
        "points": len(points.xyz),
        "packets": len(payloads),
        "synthetic": False,
    }
    import tempfile

    _tests_importable()
    from tests.drivers.test_robosense_packet import _write_ruby_table, encode_ruby128, expected_ruby128_points

    with tempfile.TemporaryDirectory() as folder:
        ruby = robosense_decoder("robosense-ruby128", _write_ruby_table(Path(folder) / "ruby128.csv"))
    packets, raw, azimuth = encode_ruby128(200 if quick else 1000)
    points = ruby.decode(packets)
    expected = expected_ruby128_points(raw, azimuth)
    figures["Ruby-128"] = {
        "max_abs_err_m": float(np.abs(points.xyz - expected[:, :3]).max()),
        "reference": "float64 geometry from the MSOP layout, self-made packets and angle table",
        "points": len(points.xyz),
        "packets": len(packets),
        "synthetic": True,
    }
    cpu, _ = time_medians([lambda: decoder.decode(payloads), lambda: ruby.decode(packets)], repeats)
    return {model: {"points_per_s": round(f["points"] / t)} | f for (model, f), t in zip(figures.items(), cpu,
                                                                                       strict=True)}
