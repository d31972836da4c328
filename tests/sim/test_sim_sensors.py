"""The simulator's sensors against its ground truth: projected lane markings land on the rendered marking
pixels, cars occlude, the cameras' photometry differs; Lidar packets decode in ouster-sdk to the simulator's
own rays and lie on the true surface; GNSS, IMU and CAN bytes parse with pynmea2, pyubx2 and cantools."""

from pathlib import Path

import cantools
import numpy as np
import pynmea2
import pytest
from pyubx2 import UBXReader

from daemon.spine.config import load_config
from daemon.spine.local_frame import LocalFrame
from daemon.spine.semantic_classes import SemanticClass
from sim.sensors import can_sim, gnss_sim, imu_sim
from sim.sensors.camera_renderer import camera_pose, camera_rig, project_points, render_view
from sim.sensors.camera_response import expose, vignetting_map
from sim.sensors.lidar_sim import ouster_rig, simulate_scan
from sim.sensors.semantic_mask_sim import segmentation_mask
from sim.world.road_world import height_st, road_point, surface_height
from sim.world.scenarios import load_scenario
from sim.world.scene import build_scene

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
CONFIG = load_config(CONFIGS / "sim.yaml")


@pytest.fixture(scope="module")
def city():
    return build_scene(load_scenario("city"), CONFIG, 4.0)


def _image(scene, cam, view, seed=0):
    vignette = vignetting_map(cam.width, cam.height, cam.intrinsics.cx, cam.intrinsics.cy, cam.photometry.vignetting)
    light = scene.scenario.lighting
    return expose(view.radiance, cam.photometry, vignette, light.exposure, light.noise_scale, seed)


def _marking_points(scene, s_lo, s_hi):
    """Interior texels of lane markings (all 8 neighbours marking too) between arc lengths s_lo and s_hi."""
    atlas = scene.world.atlas
    r0, r1 = int(s_lo / atlas.res), int(s_hi / atlas.res)
    sem = atlas.semantic[r0 - 1:r1 + 1]
    mark = sem == SemanticClass.LANE_MARKING
    inner = mark[1:-1, 1:-1].copy()
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            inner &= mark[1 + dr:mark.shape[0] - 1 + dr, 1 + dc:mark.shape[1] - 1 + dc]
    rows, cols = np.nonzero(inner)
    s = atlas.s0 + (rows + r0 + 0.5) * atlas.res
    t = atlas.t0 + (cols + 1 + 0.5) * atlas.res
    xy = road_point(scene.world, s, t)
    return np.column_stack([xy, height_st(scene.world, s, t)])


def test_projected_lane_markings_land_on_marking_pixels(city):
    time_s = 2.0
    ego_s = float(city.ego.sample("s", np.array([time_s]))[0])
    points = _marking_points(city, ego_s + 4, ego_s + 30)
    for cam in CONFIG.sensors.cameras:
        rig = camera_rig(cam)
        view = render_view(city, rig, time_s)
        rot, origin = camera_pose(city, rig, time_s)
        px, front = project_points(rig, rot, origin, points)
        col, row = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
        inside = front & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        col, row, pts = col[inside], row[inside], points[inside]
        distance = np.linalg.norm(pts - origin, axis=1)
        visible = np.abs(view.depth[row, col] - distance) < 0.3  # not behind a car
        on_marking = view.labels[row, col] == SemanticClass.LANE_MARKING
        # Within 12 m a pixel spans under 10 cm of road, so the rounded pixel stays on the marking.
        near = visible & (distance < 12)
        assert near.sum() > 200, cam.name
        assert on_marking[near].mean() > 0.99, (cam.name, on_marking[near].mean())
        assert on_marking[visible].mean() > 0.85, (cam.name, on_marking[visible].mean())
        image = _image(city, cam, view)
        grey = image.astype(float).mean(axis=2)
        road = view.labels == SemanticClass.ROAD
        assert np.median(grey[row[near], col[near]]) > np.median(grey[road]) + 40
        mask = segmentation_mask(view.labels, view.depth, np.random.default_rng(1))
        agree = (mask == view.labels).mean()
        assert 0.9 < agree < 1.0  # a network's mask: mostly right, never perfect


def test_cars_occlude_the_road_and_cameras_differ_in_photometry(city):
    means = {}
    for cam in CONFIG.sensors.cameras:
        view = render_view(city, camera_rig(cam), 1.0)
        car = view.labels == SemanticClass.OBSTACLE
        assert car.any(), cam.name  # heavy traffic: every camera sees a car
        ground = np.isfinite(view.depth) & ~car
        assert np.isfinite(view.depth[car]).all()
        image = _image(city, cam, view).astype(float)
        road = view.labels == SemanticClass.ROAD
        means[cam.name] = image[road].mean(axis=0)
        assert ground.any()
    wide, left, right = means["front_wide"], means["front_left"], means["front_right"]
    assert wide.mean() > 1.08 * left.mean()  # gain 1.15 against 0.75 (gamma 1.1 lifts the left one)
    assert left[2] / left[0] > 1.1 > right[2] / right[0]  # left camera blue, right camera warm


def test_night_shows_only_the_headlight_lit_region():
    night = build_scene(load_scenario("night"), CONFIG, 1.0)
    cam = CONFIG.sensors.cameras[0]
    rig = camera_rig(cam)
    view = render_view(night, rig, 0.5)
    grey = _image(night, cam, view).astype(float).mean(axis=2)
    lit = grey[300:420, 380:580]  # the road ahead of the car, in the headlights' cone
    far = np.isfinite(view.depth) & (view.depth > 60)
    assert lit.mean() > 80 and grey[far].mean() < 25
    assert grey[np.isinf(view.depth)].mean() < 20


def _sdk_frame(sdk, info, packets):
    fmt = sdk.PacketFormat(info)
    batcher = sdk.FrameBatcher(info)
    frame = sdk.LidarFrame(info)
    rows = list(packets) + [packets[-1]]
    for i, row in enumerate(rows):
        packet = sdk.LidarPacket(fmt)
        packet.buf[:] = row
        if i == len(rows) - 1:
            fmt.set_frame_id(packet, (fmt.frame_id(row) + 1) % (fmt.max_frame_id + 1))
        packet.host_timestamp = i + 1
        if batcher.batch(packet, frame):
            return frame
    raise AssertionError("the SDK released no frame")


def test_lidar_packets_decode_in_ouster_sdk_to_the_simulated_rays(city):
    sdk = pytest.importorskip("ouster.sdk.core")
    lidar = CONFIG.sensors.lidar
    metadata = CONFIGS / lidar.metadata_file
    rig = ouster_rig(lidar, metadata)
    scan = simulate_scan(city, rig, 7, 1.5, np.random.default_rng(3))
    stamps = (scan.column_time_s * 1e9).astype(np.int64) + 1_700_000_000_000_000_000
    packets, packet_stamps = rig.encode(scan, stamps)
    np.testing.assert_array_equal(packet_stamps, stamps[::16])
    assert packets.shape == (64, 24896)
    info = sdk.SensorInfo(metadata.read_text())
    frame = _sdk_frame(sdk, info, packets)
    assert frame.frame_id == 7
    np.testing.assert_array_equal(frame.timestamp, stamps)
    ranges = frame.field("RANGE")
    np.testing.assert_array_equal(ranges, scan.range_mm)
    xyz = sdk.XYZLut(info)(ranges)  # (H, W, 3) sensor frame
    valid = ranges > 0
    assert valid.mean() > 0.3
    # Each column's sensor pose at its firing time takes the SDK's points to the world.
    rot_v, pos_v = city.ego.pose(scan.column_time_s)
    rot = rot_v @ rig.sensor_to_vehicle[:3, :3]
    pos = pos_v + rot_v @ rig.sensor_to_vehicle[:3, 3]
    world = np.einsum("wij,hwj->hwi", rot, xyz) + pos[None]
    truth = np.moveaxis(scan.hit_world, 0, 1)  # (H, W, 3)
    error = np.linalg.norm(world - truth, axis=-1)[valid]
    assert np.percentile(error, 99) < 0.04 and np.median(error) < 0.015  # 1 cm range noise
    # Road returns lie on the true surface within the noise.
    road = np.moveaxis(scan.hit_class, 0, 1) == SemanticClass.ROAD
    pts = world[valid & road]
    height = surface_height(city.world, pts[:, 0].astype(np.float32), pts[:, 1].astype(np.float32))
    assert len(pts) > 5000
    assert np.percentile(np.abs(pts[:, 2] - height), 99) < 0.04
    # Cars return too, above the road.
    assert (np.moveaxis(scan.hit_class, 0, 1)[valid] == SemanticClass.OBSTACLE).sum() > 500


def test_gnss_bytes_parse_and_hold_the_antenna_position(city):
    sc = city.scenario
    frame = LocalFrame(sc.origin.latitude_deg, sc.origin.longitude_deg, sc.origin.altitude_m)
    times = np.arange(0.1, 3.0, 0.1)
    utc = 1_780_308_000_000_000_000 + np.rint(times * 1e9).astype(np.int64)
    lever = np.array(CONFIG.sensors.gnss.antenna_lever_arm_m)
    epochs = gnss_sim.antenna_epochs(city.ego, frame, lever, times, utc, "rtk", np.random.default_rng(0))
    rot, pos = city.ego.pose(times)
    truth = pos + rot @ lever
    errors = []
    for epoch, true_enu in zip(epochs, truth, strict=True):
        data = gnss_sim.epoch_bytes(epoch)
        text, ubx = data[:data.index(b"\xb5\x62")], data[data.index(b"\xb5\x62"):]
        sentences = [pynmea2.parse(line, check=True) for line in text.decode().split("\r\n") if line]
        assert [s.sentence_type for s in sentences] == ["RMC", "GGA", "GST"]
        gga = sentences[1]
        assert gga.gps_qual == 4
        enu = frame.geodetic_to_enu(gga.latitude, gga.longitude, gga.altitude)
        errors.append(enu - true_enu)
        pvt = UBXReader.parse(ubx)
        assert pvt.identity == "NAV-PVT" and pvt.carrSoln == 2
        assert pvt.lat == pytest.approx(gga.latitude, abs=2e-7) and pvt.lon == pytest.approx(gga.longitude, abs=2e-7)
        speed = np.hypot(pvt.velN, pvt.velE) / 1000
        assert speed == pytest.approx(float(sentences[0].spd_over_grnd) * 0.514444, abs=0.01)
    errors = np.array(errors)
    assert np.abs(errors[:, :2]).max() < 0.06 and np.abs(errors[:, 2]).max() < 0.1
    assert np.abs(errors).max() > 0.001  # noisy, not the truth


def test_imu_esf_raw_parses_to_the_car_motion(city):
    times = np.arange(0.0, 2.0, 0.01)
    force, rate = imu_sim.imu_readings(city.ego, np.eye(4), times, np.random.default_rng(0))
    assert np.abs(np.median(force[:, 2]) - 9.81) < 0.1  # gravity, the car level-ish
    assert np.abs(force[:, 0] - np.median(force[:, 0])).max() < 1.5
    data = imu_sim.esf_raw_bytes(force[10], rate[10], tick=(1 << 24) + 12345)
    msg = UBXReader.parse(data)
    assert msg.identity == "ESF-RAW"
    words = {int.from_bytes(getattr(msg, f"data_{i:02d}"), "little") >> 24:
             int.from_bytes(getattr(msg, f"data_{i:02d}"), "little") & 0xFFFFFF for i in range(1, 7)}
    signed = {k: v - (1 << 24) if v >= 1 << 23 else v for k, v in words.items()}
    assert signed[18] * imu_sim.ACCEL_LSB == pytest.approx(force[10, 2], abs=1e-3)
    assert np.radians(signed[5] * 2.0**-12) == pytest.approx(rate[10, 2], abs=1e-4)
    assert int.from_bytes(msg.sTag_01, "little") == 12345


def test_can_frames_decode_with_cantools_to_the_wheel_speeds(city):
    can_cfg = CONFIG.sensors.can
    db = cantools.database.load_file(str(CONFIGS / can_cfg.dbc_file), strict=False)
    times = np.arange(0.0, 2.0, 1 / can_sim.RATE_HZ)
    speeds, yaw = can_sim.wheel_speeds(city.ego, CONFIG.vehicle, times, np.random.default_rng(0))
    assert np.abs(speeds.mean(axis=1) - city.ego.sample("speed", times)).max() < 0.15
    frames = can_sim.can_messages(db, can_cfg.signals, speeds, yaw)
    for i in (0, 50, 99):
        yaw_frame, wheel_frame = frames[i]
        wheels = db.decode_message(wheel_frame.arbitration_id, wheel_frame.data)
        assert wheels["WHEEL_SPEED_FL"] / 3.6 == pytest.approx(speeds[i, 0], abs=0.01)
        assert wheels["WHEEL_SPEED_RR"] / 3.6 == pytest.approx(speeds[i, 3], abs=0.01)
        dyn = db.decode_message(yaw_frame.arbitration_id, yaw_frame.data)
        assert np.radians(dyn["YAW_RATE"]) == pytest.approx(yaw[i], abs=0.001)
