"""A point-cloud Lidar's log maps as its packet log does: the simulated city drive with its Ouster scans decoded into
PointClouds (tests/point_cloud_logs.py) against the drive as recorded, through `load_drive`, `roadlog reconstruct`
and the live worker fed by a replay over the bus.

Tolerance: the point records carry each point's time as float32 seconds after the scan's start, which holds a
column's time to within 4 ns of the packet's nanoseconds; at 10 m/s that moves a deskewed point by < 0.1 um. So the
Lidar ground is the same points, in the same order, each within 1e-6 m of the packet log's (measured: 4e-8 m). The
fits are deterministic but not smooth in their inputs (a point moved across a triangle edge pulls another vertex), so
the maps' figures differ a little: Elev-error and the error against the truth within 0.05 cm, a tenth of the
live-vs-reconstruct tolerance (measured: 0.0002 and 0.0006 cm), PSNR within 0.5 dB and mIoU within 2 points
(measured: 0.12 dB, 0.17 points)."""

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from daemon.bus import pubsub
from daemon.processes.replay import replay
from daemon.spine.config import load_config
from daemon.spine.topics import LIDAR_POINTS
from mapping.inputs.drive_inputs import check_config, load_drive
from mapping.live.worker_loop import MappingWorker
from mapping.offline.reconstruct_command import DriveTruth, config_from_logs
from mapping.offline.reconstruct_command import main as reconstruct_main
from tests.daemon_fixtures import REPO, private_config
from tests.point_cloud_logs import point_cloud_log

SMALL_WINDOWS = {"windows": {"before_m": 10.0, "after_m": 10.0}, "mesh": {"side_m": 0.25, "corridor_half_width_m": 6.0},
                 "inputs": {"keyframe_spacing_m": 2.0}}


@pytest.fixture(scope="module")
def points_drive(city_drive, tmp_path_factory):
    """The session's 5 s city drive (packets) and the same drive as a point-cloud Lidar's log."""
    return city_drive, point_cloud_log(city_drive, tmp_path_factory.mktemp("points") / "city_points.mcap")


def test_a_point_cloud_log_gives_the_lidar_ground_of_its_packet_log(points_drive):
    packets_log, points_log = points_drive
    truth = DriveTruth.load(packets_log.with_name("city.gt.npz"))
    packets_config = load_config(REPO / "configs" / "sim.yaml")
    points_config, points_path = config_from_logs([str(points_log)])  # recorded: a point-cloud Lidar, no metadata
    assert points_config.sensors.lidar.point_clouds and points_config.sensors.lidar.metadata_file is None
    check_config(points_config, points_path)  # the mapper's start-up check asks it for no metadata
    for every_n in (2, 3):  # the default, and another: the same scans are kept
        inputs = {"lidar_every_n_scans": every_n}
        a, b = (load_drive([log], config.model_copy(update={"mapper": config.mapper.model_copy(update={
            "inputs": config.mapper.inputs.model_copy(update=inputs)})}), path, origin=truth.origin)
            for log, config, path in ((packets_log, packets_config, REPO / "configs" / "sim.yaml"),
                                      (points_log, points_config, points_path)))
        assert b.counts["lidar_point_clouds"] == a.counts["lidar_packets"] / 64  # one cloud per scan of 64 packets
        assert b.clocks[LIDAR_POINTS].kind == "utc" and "lidar/packets" not in b.clocks
        ground_a, ground_b = a.lidar_ground_points, b.lidar_ground_points
        assert len(ground_a) > 10_000 * (4 - every_n)
        # the same points within float32 rounding (the cloud log stores float32), so the ground filter's thresholds
        # may take or drop a point lying on them differently: 1 of 446,706 at every 2nd scan since the fusion's
        # fixes weigh x3 (a43e398)
        assert abs(len(ground_a) - len(ground_b)) <= 1e-4 * len(ground_a), (every_n, len(ground_a), len(ground_b))
        distance, _ = cKDTree(ground_b).query(ground_a)
        assert np.mean(distance < 1e-6) > 1 - 1e-4, every_n


def _reconstruct(log, out, truth_path) -> dict:
    assert reconstruct_main([str(log), "--out", str(out), "--gt", str(truth_path)]) == 0
    return json.loads((out / "metrics.json").read_text())


def test_reconstruct_maps_a_point_cloud_log_as_its_packet_log(points_drive, tmp_path):
    packets_log, points_log = points_drive
    truth = packets_log.with_name("city.gt.npz")
    a = _reconstruct(packets_log, tmp_path / "packets", truth)
    b = _reconstruct(points_log, tmp_path / "points", truth)
    points_a, points_b = a["inputs"]["lidar_ground_points"], b["inputs"]["lidar_ground_points"]
    assert points_a > 10_000 and abs(points_b - points_a) <= 1e-4 * points_a, (points_a, points_b)  # float32 clouds
    assert b["lidar_supervision"] and b["inputs"]["lidar_point_clouds"] > 0 and "lidar_packets" not in b["inputs"]
    assert b["elev_error_cm"] < 3
    assert abs(b["elev_error_cm"] - a["elev_error_cm"]) < 0.05
    assert abs(b["elev_mae_gt_cm"] - a["elev_mae_gt_cm"]) < 0.05
    assert abs(b["psnr_db"] - a["psnr_db"]) < 0.5 and abs(b["miou_pct"] - a["miou_pct"]) < 2


def _window_through_the_bus(log, folder, point_clouds: bool):
    """Window 0 of the worker (in this process) fed the log by a replay over the real bus, as fast as it takes it."""
    folder.mkdir()
    config, config_path = private_config(folder, point_clouds=point_clouds, mapper=SMALL_WINDOWS)
    worker = MappingWorker(config, str(config_path), str(folder / "data"))
    try:
        for topic in worker.reader.topics:  # the rings exist before the worker subscribes, as the daemon makes them
            pubsub.open_publisher(config, topic).close()
        worker.reader.attach()  # lossless: the player waits for it
        worker.reader.start()
        progress = replay(config, [log], rate=None)
        worker.reader.stop_requested.set()
        assert worker.reader.drained.wait(60)
        worker.update_distance()
        return worker, progress, worker.run_window(0).to_json()
    finally:
        pubsub.unlink_all(config)


def test_the_live_worker_maps_a_point_cloud_log_replayed_onto_the_bus(points_drive, tmp_path):
    packets_log, points_log = points_drive
    worker, progress, b = _window_through_the_bus(points_log, tmp_path / "points", point_clouds=True)
    assert progress.published[LIDAR_POINTS] == 49 and not progress.skipped  # the player plays it in the driver's place
    assert worker.reader.lost == 0 and worker.reader.lidar_count == 49
    spooled = [m for _, _, m in worker.spool.read(0, 2**62, {LIDAR_POINTS})]
    assert [m.seq for m in spooled] == list(range(0, 49, 2))  # every 2nd scan (mapper.inputs.lidar_every_n_scans)
    assert b["status"] == "done" and b["lidar_point_clouds"] > 0 and "lidar_packets" not in b
    _, _, a = _window_through_the_bus(packets_log, tmp_path / "packets", point_clouds=False)
    # the spool gives a window what arrived up to 1 s past its end: a scan's packets up to then, its point cloud only
    # when the whole scan is in; so the packet window may hold a partial scan more, and the ground points of up to
    # one more scan
    assert b["lidar_point_clouds"] == a["lidar_packets"] // 64 and b["keyframes"] == a["keyframes"]
    assert 0 <= a["lidar_ground_points"] - b["lidar_ground_points"] < b["lidar_ground_points"] / b["lidar_point_clouds"]
    assert b["lidar_ground_points"] > 5_000
    assert abs(b["metrics"]["elev_error_cm"] - a["metrics"]["elev_error_cm"]) < 0.05
