"""The `vendors` figures of bench/lidar.py: per Lidar model beyond Ouster, our decoder's points/s on one
core on the shared real captures, its largest xyz difference from the model's reference decoder, and
the reference's own points/s measured side by side (Velodyne: velodyne-decoder 3.1.0, C++)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.velodyne_calibration import load_velodyne_calibration
from drivers.lidar.velodyne_decoder import VelodyneDecoder

NEBULA = Path("/work/shared/data/lidar_nebula")
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


def robosense_figures(quick: bool) -> dict:
    """{model: figures} for RoboSense: our decoder's points/s on one core (CPU seconds of this thread,
    median of repeats) and its largest xyz difference from the reference. Helios-16P: the shared real capture,
    against Nebula's decoded cloud of its first rotation (no Python decoder exists to time beside it).
    Ruby-128: packets from the test-side encoder (synthetic), against the float64 geometry that test computes."""
    import statistics
    import time

    from drivers.lidar.robosense_decoder import robosense_decoder

    repeats = 3 if quick else 9

    def median_cpu(run: Callable[[], object]) -> float:
        run()
        times = []
        for _ in range(repeats):
            start = time.thread_time()
            run()
            times.append(time.thread_time() - start)
        return statistics.median(times)

    figures = {}
    payloads = [d.payload for d in read_pcap_udp(NEBULA / "robosense" / "helios16P.pcap").datagrams]
    decoder = robosense_decoder("robosense-helios16p", NEBULA / "calib" / "RobosenseHelios16P.csv")
    points = decoder.decode(payloads)
    reference = np.loadtxt(NEBULA / "robosense" / "helios16P.reference.pcd", skiprows=11)
    error = np.abs(points.xyz[: len(reference)].astype(np.float64) - reference[:, :3]).max(axis=1)
    figures["Helios-16P"] = {
        "points_per_s": round(len(points.xyz) / median_cpu(lambda: decoder.decode(payloads))),
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
        "points_per_s": round(len(points.xyz) / median_cpu(lambda: ruby.decode(packets))),
        "max_abs_err_m": float(np.abs(points.xyz - expected[:, :3]).max()),
        "reference": "float64 geometry from the MSOP layout, self-made packets and angle table",
        "points": len(points.xyz),
        "packets": len(packets),
        "synthetic": True,
    }
    return figures
