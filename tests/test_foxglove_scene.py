"""A drive as Foxglove's 3D panel shows it, from a log the real daemon recorded while replaying a simulated drive (the
player, recorder, `lidar_view` and `vehicle_pose` processes over the real bus): the viewing clouds and the live pose are
in it (read back with our reader and the mcap library), and an independent reader, the TypeScript @mcap/core with
protobufjs decoding each message from the schema stored in the log (node, from npm into tests/.node/; skipped with
the reason when it cannot be installed), finds what the panel needs: the frames chain map -> vehicle -> lidar / each
camera at the clouds' and the images' times, the clouds' frame_id among the frames, the car moving with the drive."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from daemon.bus.pubsub import unlink_all
from daemon.log_format.metadata_records import LOG_TIME_OFFSET_KEY
from daemon.log_format.reader import read_log, read_metadata
from daemon.spine.topics import (
    GNSS_FIX,
    LIDAR_VIEW,
    MAP_FRAME,
    TF,
    TF_STATIC,
    VEHICLE_FRAME,
    VEHICLE_POSE,
    VEHICLE_POSE_PROCESS,
    camera_topic,
    health_topic,
)
from tests.daemon_fixtures import private_config
from tests.node_packages import node_modules as installed
from tests.roadlog_cli import roadlog

SCENE_JS = Path(__file__).with_name("foxglove_scene.js")
POSE_GAP_NS = 150_000_000  # the live pose is at 10 Hz: a time between two poses this close is on the chain
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def replayed(city_drive, tmp_path_factory):
    """The segment the daemon recorded replaying the city drive at its own speed, and its config."""
    tmp = tmp_path_factory.mktemp("scene")
    config, path = private_config(tmp, mapper={"enabled": False}, status={"port": 0})
    try:
        run = roadlog("replay", city_drive, "--config", path, "--rate", "1.0", "--output-dir", tmp / "out", cwd=tmp,
                      timeout=240)
    finally:
        unlink_all(config)
    assert run.returncode == 0, run.stderr[-3000:]
    [segment] = sorted((tmp / "out").glob("roadlog_*.mcap"))
    return segment, config


def test_the_replayed_log_holds_viewing_clouds_and_the_live_pose(replayed):
    segment, config = replayed
    back: dict[str, list] = {}
    for rec in read_log([segment], topics={LIDAR_VIEW, VEHICLE_POSE, camera_topic("front_wide")}):
        back.setdefault(rec.topic, []).append(rec.message)
    drive_s = (max(m.host_mono_ns for m in back[camera_topic("front_wide")])
               - min(m.host_mono_ns for m in back[camera_topic("front_wide")])) / 1e9
    clouds, poses = back[LIDAR_VIEW], back[VEHICLE_POSE]
    assert abs(len(clouds) - drive_s * config.recorder.point_cloud_view_hz) <= 2, (len(clouds), drive_s)
    assert all(c.sensor == "lidar" and len(c.data) > 20 * 10_000 for c in clouds)
    assert len(poses) >= 0.8 * drive_s * config.recorder.pose_hz  # from the first fix to the end (the last at the stop)
    assert all(p.frame_id == MAP_FRAME for p in poses)
    assert json.loads(read_metadata(segment)["roadlog.counts"]["lost_per_topic"]) == {}
    # the map frame's origin (the process's first GNSS fix) is in its health reports the log holds
    fixes = [rec.message for rec in read_log([segment], topics={GNSS_FIX})]
    origins = [json.loads(rec.message.detail)["map_origin"]
               for rec in read_log([segment], topics={health_topic(VEHICLE_POSE_PROCESS)})]
    assert origins and all(o == origins[-1] for o in origins if o is not None) and origins[-1] is not None
    assert (origins[-1]["lat_deg"], origins[-1]["lon_deg"]) in {(f.latitude_deg, f.longitude_deg) for f in fixes[:5]}
    with open(segment, "rb") as f:  # each pose again as the transform map -> vehicle, at the same log time
        tfs = [(message.log_time, message.publish_time) for _, _, message in make_reader(f).iter_messages([TF])]
    offset = int(read_metadata(segment)["roadlog"][LOG_TIME_OFFSET_KEY])
    assert tfs == [(p.host_mono_ns + offset, p.sensor_time_ns) for p in poses]


@pytest.fixture(scope="module")
def node_modules() -> Path:
    """tests/.node/node_modules with @mcap/core, lz4js and protobufjs."""
    return installed("@mcap/core@2", "lz4js@0.2", "protobufjs@7")


def foxglove_view(node_modules: Path, segment: Path) -> dict:
    done = subprocess.run(["node", str(SCENE_JS), str(segment)], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, NODE_PATH=str(node_modules)), check=True)
    view = json.loads(done.stdout)
    assert view["done"]
    return view["topics"]


def test_foxglove_finds_the_frames_chain_at_every_cloud_and_image_and_the_car_moves(replayed, node_modules):
    segment, config = replayed
    topics = foxglove_view(node_modules, segment)
    assert topics[TF]["schema"] == "foxglove.FrameTransform"
    assert topics[TF_STATIC]["schema"] == "foxglove.FrameTransforms"
    assert topics[LIDAR_VIEW]["schema"] == "foxglove.PointCloud"
    assert topics[VEHICLE_POSE]["schema"] == "foxglove.PoseInFrame"
    # the static transforms: one message, vehicle -> every sensor (a frame with one transform holds at every time)
    [static] = topics[TF_STATIC]["messages"]
    sensors = {tf["child"] for tf in static["transforms"] if tf["parent"] == VEHICLE_FRAME}
    cameras = [cam.name for cam in config.sensors.cameras]
    assert {"lidar", *cameras} <= sensors
    static_t = max(int(tf["t"]) for tf in static["transforms"])  # Foxglove looks up the newest at or before a stamp
    # the moving one: map -> vehicle, every pose once
    tfs = topics[TF]["messages"]
    assert {(tf["parent"], tf["child"]) for tf in tfs} == {(MAP_FRAME, VEHICLE_FRAME)}
    tf_times = np.array([int(tf["t"]) for tf in tfs])
    assert np.all(np.diff(tf_times) > 0)
    poses = topics[VEHICLE_POSE]["messages"]
    assert [p["t"] for p in poses] == [tf["t"] for tf in tfs]
    assert [p["position"] for p in poses] == [tf["translation"] for tf in tfs]

    def on_the_chain(t: int) -> bool:
        """A pose at or around t (Foxglove interpolates between the two nearest)."""
        i = np.searchsorted(tf_times, t)
        return (i < len(tf_times) and tf_times[i] == t) or (
            0 < i < len(tf_times) and tf_times[i] - tf_times[i - 1] <= POSE_GAP_NS)

    clouds = topics[LIDAR_VIEW]["messages"]
    assert {c["frame_id"] for c in clouds} == {"lidar"} and all(c["points"] > 10_000 for c in clouds)
    assert {"x", "y", "z", "intensity"} <= set(clouds[0]["fields"])
    images = [m for cam in cameras for m in topics[camera_topic(cam)]["messages"]]
    assert {m["frame_id"] for m in images} == set(cameras)
    for what, messages in (("clouds", clouds), ("images", images)):
        times = [int(m["t"]) for m in messages]
        within = [t for t in times if tf_times[0] <= t <= tf_times[-1]]
        assert all(map(on_the_chain, within)), what
        assert all(static_t <= t for t in times), what  # the sensor frames hold at every payload stamp
        # the poses span the drive from its first fix to its end (the last fusion at the stop)
        assert len(within) >= 0.8 * len(times), (what, len(within), len(times))
    # the car moves with the drive: the city drive goes at ~9 m/s
    track = np.array([tf["translation"] for tf in tfs])
    seconds = (tf_times[-1] - tf_times[0]) / 1e9
    path_m = np.linalg.norm(np.diff(track[:, :2], axis=0), axis=1).sum()
    assert 5 * seconds < path_m < 15 * seconds, (path_m, seconds)
    assert np.linalg.norm(track[-1, :2] - track[0, :2]) > 0.8 * path_m  # along the road, not jittering in place
