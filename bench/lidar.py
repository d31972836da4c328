"""Ouster decode throughput on one core: packets -> XYZ with our batch decoder and with ouster-sdk
(FrameBatcher + XYZLut) on the same OS-128 2048x10 LEGACY packets, made by our encoder.

Under `vendors`, the other models decoded, on the shared real captures (bench/lidar_vendors.py).

`realtime_factor` (Ouster) and each vendor's `realtime_factor_128` are points/s over a 128-beam sensor's real rate
(SENSOR_POINTS_PER_S); issue 16's target is REALTIME_FACTOR_TARGET for every vendor model (`vendors_below_target`).

Run: .venv/bin/python bench/lidar.py [--quick]. Last line: JSON with points_per_s, ouster_sdk_ratio, vendors."""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from lidar_vendors import hdl64e_figures, hesai_figures, robosense_figures, velodyne_figures  # noqa: E402

from drivers.lidar.lidar_points import batch_xyz, scan_point_cloud  # noqa: E402
from drivers.lidar.ouster_decoder import decode_packets, ouster_scan_assembler  # noqa: E402
from drivers.lidar.ouster_encoder import encode_frame_packets  # noqa: E402
from drivers.lidar.ouster_metadata import metadata_to_json, simulated_os128_metadata  # noqa: E402
from drivers.lidar.ouster_packet_layout import packet_layout  # noqa: E402
from drivers.lidar.ouster_xyz import make_xyz_lut  # noqa: E402

SENSOR_POINTS_PER_S = 2048 * 128 * 10  # an OS-128 at 2048x10: 2.62 M points/s, the 128-beam rate the targets count in
REALTIME_FACTOR_TARGET = 20  # issue 16: every vendor decoder at least 20x a 128-beam sensor's point rate on one core


def make_frames(layout, n_frames: int, seed: int = 0) -> list[np.ndarray]:
    """n_frames of packets, (128, 24896) uint8 each: ranges 0.3-120 m, 15 % without return."""
    rng = np.random.default_rng(seed)
    h, w = layout.pixels_per_column, layout.columns_per_frame
    frames = []
    for f in range(n_frames):
        ranges = rng.integers(300, 120_000, (h, w))
        ranges[rng.random((h, w)) < 0.15] = 0
        pixels = {
            "range_mm": ranges,
            "reflectivity": rng.integers(0, 256, (h, w)),
            "signal": rng.integers(0, 4000, (h, w)),
            "near_ir": rng.integers(0, 4000, (h, w)),
        }
        timestamps = np.uint64(10**18) + np.arange(w, dtype=np.uint64) * np.uint64(48_828)
        frames.append(encode_frame_packets(layout, f, pixels, timestamps))
    return frames


def time_medians(runs: list, repeats: int) -> tuple[list[float], list[float]]:
    """Median CPU time (of this thread: what one core spent, whatever else shares the machine) and
    median wall time of each run, the runs taking turns so that they see the same machine state."""
    cpu: list[list[float]] = [[] for _ in runs]
    wall: list[list[float]] = [[] for _ in runs]
    for run in runs:
        run()  # warm up
    for _ in range(repeats):
        for i, run in enumerate(runs):
            start_cpu, start_wall = time.thread_time(), time.perf_counter()
            run()
            cpu[i].append(time.thread_time() - start_cpu)
            wall[i].append(time.perf_counter() - start_wall)
    return [statistics.median(t) for t in cpu], [statistics.median(t) for t in wall]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer frames and repetitions (< 1 min)")
    parser.add_argument("--core", type=int, default=0, help="CPU core to pin to")
    args = parser.parse_args()
    os.sched_setaffinity(0, {args.core})
    n_frames, repeats = (5, 5) if args.quick else (20, 9)

    meta = simulated_os128_metadata(2048)
    layout = packet_layout(meta)
    lut = make_xyz_lut(meta)
    frames = make_frames(layout, n_frames)
    points = n_frames * meta.columns_per_frame * meta.pixels_per_column
    datagram_lists = [[bytes(row) for row in frame] for frame in frames]

    def ours_array() -> None:  # receive buffer as a socket driver fills it
        for frame in frames:
            batch_xyz(decode_packets(frame, layout), lut)

    def ours_bytes() -> None:  # one bytes object per datagram
        for datagrams in datagram_lists:
            batch_xyz(decode_packets(datagrams, layout), lut)

    def ours_decode_only() -> None:
        for frame in frames:
            decode_packets(frame, layout)

    def ours_to_clouds() -> None:  # decode, assemble scans, point clouds of the returns
        assembler = ouster_scan_assembler(layout)
        for frame in frames:
            for scan in assembler.add(decode_packets(frame, layout)):
                scan_point_cloud(scan, lut)

    import ouster.sdk.core as sdk

    info = sdk.SensorInfo(metadata_to_json(meta))
    fmt = sdk.PacketFormat(info)
    sdk_lut = sdk.XYZLut(info)
    sdk_packets = []
    for frame in frames:
        for i, row in enumerate(frame):
            packet = sdk.LidarPacket(fmt)
            packet.buf[:] = row
            packet.host_timestamp = i + 1
            sdk_packets.append(packet)

    def sdk_run() -> None:
        batcher = sdk.FrameBatcher(info)
        scan = sdk.LidarFrame(info)
        done = 0
        for packet in sdk_packets:
            if batcher.batch(packet, scan):
                sdk_lut(scan)
                done += 1
        assert done == n_frames, done

    (t_ours, t_sdk, t_bytes, t_decode, t_clouds), (w_ours, w_sdk, *_) = time_medians(
        [ours_array, sdk_run, ours_bytes, ours_decode_only, ours_to_clouds], repeats
    )
    results = {
        "points_per_s": points / t_ours,
        "ouster_sdk_points_per_s": points / t_sdk,
        "ouster_sdk_ratio": t_sdk / t_ours,
        "points_per_s_wall_clock": points / w_ours,
        "ouster_sdk_ratio_wall_clock": w_sdk / w_ours,
        "points_per_s_bytes_input": points / t_bytes,
        "points_per_s_decode_only": points / t_decode,
        "points_per_s_to_point_clouds": points / t_clouds,
    }
    results["realtime_factor"] = results["points_per_s"] / SENSOR_POINTS_PER_S
    vendors = velodyne_figures(time_medians, repeats)
    vendors |= hdl64e_figures(time_medians, repeats)
    vendors |= hesai_figures(time_medians, repeats)
    vendors |= robosense_figures(time_medians, repeats, args.quick)
    for figures in vendors.values():
        figures["realtime_factor_128"] = round(figures["points_per_s"] / SENSOR_POINTS_PER_S, 2)
    below_target = [model for model, figures in vendors.items()
                    if figures["realtime_factor_128"] < REALTIME_FACTOR_TARGET]
    print(
        f"OS-128 2048x10 LEGACY, {n_frames} frames x 128 packets, median of {repeats}, core {args.core}, "
        "points/s per CPU-second of this thread unless wall_clock"
    )
    for name, value in results.items():
        print(
            f"  {name:32s} {value / 1e6:10.1f} M"
            if name.startswith("points") or "sdk_points" in name
            else f"  {name:32s} {value:10.2f}"
        )
    print("vendors (real captures; reference: the model's reference decoder)")
    for model, figures in vendors.items():
        error = "" if figures["max_abs_err_m"] is None else f"  max_abs_err_m {figures['max_abs_err_m']:.1e}"
        reference = (
            f"  {figures['reference']} {figures['reference_points_per_s'] / 1e6:6.1f} M "
            f"(ratio {figures['reference_ratio']:.2f})"
            if "reference_points_per_s" in figures
            else f"  reference: {figures['reference']}"
        ) + ("  [synthetic]" if figures.get("synthetic") else "")
        print(f"  {model:18s} points_per_s {figures['points_per_s'] / 1e6:6.1f} M "
              f"(x{figures['realtime_factor_128']:5.1f} of 128 beams){error}{reference}")
    print(f"vendors below {REALTIME_FACTOR_TARGET}x a 128-beam sensor's rate: {', '.join(below_target) or 'none'}")
    print(
        json.dumps(
            {k: round(v, 3) if v < 1e3 else round(v) for k, v in results.items()}
            | {"frames": n_frames, "repeats": repeats, "xyz_dtype": "float32 (sdk: float64)", "vendors": vendors,
               "vendor_realtime_factor_128_target": REALTIME_FACTOR_TARGET, "vendors_below_target": below_target}
        )
    )


if __name__ == "__main__":
    main()
