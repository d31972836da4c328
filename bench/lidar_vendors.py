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
