"""`roadlog reconstruct` as a user runs it: a recorded simulated drive (MCAP), its config taken from the log's
own metadata, the truth beside it; the files and metrics it writes."""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import rasterio
import trimesh
import yaml
from rasterio.warp import transform

from daemon.log_format.writer import LogWriter
from daemon.spine.config import ConfigError, config_to_yaml, load_config
from daemon.spine.local_frame import LocalFrame
from mapping.offline.reconstruct_command import config_from_logs
from tests.daemon_fixtures import REPO


def test_reconstruct_a_recorded_drive_against_its_truth(city_drive, tmp_path):
    out = tmp_path / "map"
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    run = subprocess.run([sys.executable, "-m", "daemon.commands.cli", "reconstruct", str(city_drive),
                          "--out", str(out),
                          "--gt", str(city_drive.with_name("city.gt.npz"))],
                         cwd=REPO, capture_output=True, text=True, timeout=600,
                         env={**os.environ, "TMPDIR": str(scratch)})
    assert run.returncode == 0, run.stderr[-3000:]
    assert not list(scratch.glob("roadlog-*"))  # the recorded config's scratch folder is gone with the process
    # every phase is reported as it ends, with the time since the start and its own: never silent for long (on a line
    # of its own: a progress bar redraws itself after a carriage return)
    shown = run.stderr.replace("\r", "\n")
    phases = re.findall(r"^roadlog reconstruct: \[ *([0-9.]+) s\] (.+) \(\+([0-9.]+) s\)$", shown, re.MULTILINE)
    names = [name for _, name, _ in phases]
    for expected in ("reading 1 log(s)", "drive path read", "mesh and model built", "Lidar ground points read",
                     "elevation fitted", "camera frames read", "keyframes observed", "colour fitted",
                     "evaluated on the held-out views", "map exported", "metrics.json and config.yaml written"):
        assert sum(name.startswith(expected) for name in names) == 1, (expected, names)
    elapsed = [float(t) for t, _, _ in phases]
    own = sum(float(d) for _, _, d in phases)
    assert elapsed == sorted(elapsed) and own == pytest.approx(elapsed[-1], abs=0.1 * len(phases))
    # each long phase has a progress bar with its total and ETA while it runs (tqdm: "desc: 42%| ... | 21/50
    # [00:03<00:04, 6.1unit/s]"), which ends at its total
    bars: dict[str, list[tuple[int, int]]] = {}
    for desc, done, total, eta in re.findall(r"^([a-z ]+): +\d+%\|[^|]*\| *(\d+)/(\d+) \[[0-9:]+<([0-9:?]+)", shown,
                                             re.MULTILINE):
        bars.setdefault(desc, []).append((int(done), int(total)))
        assert eta != "?" or int(done) == 0, (desc, done, total)
    assert {"read logs", "lidar ground", "keyframes", "elevation", "lidar detail", "observe", "colour"} <= set(bars)
    for desc, seen in bars.items():
        assert seen[-1][0] == seen[-1][1] > 0 and len({total for _, total in seen}) == 1, (desc, seen[-3:])
    printed = json.loads(run.stdout.strip().splitlines()[-1])
    metrics = json.loads((out / "metrics.json").read_text())
    assert printed["miou_pct"] == metrics["miou_pct"]
    # a 5 s drive maps worse than the 300 m drives of bench/RESULTS.md; these bounds catch a broken pipeline
    assert metrics["psnr_db"] > 20 and metrics["psnr_train_db"] > 20
    assert 40 < metrics["miou_pct"] <= 100 and 30 < metrics["miou_mask_pct"] <= 100  # bird's-eye vs truth, masks
    per_class = metrics["iou_pct"]  # the classes the drive has, each scored; their mean is miou_pct
    assert {"road", "lane_marking", "curb", "background"} <= set(per_class) and "obstacle" not in per_class
    assert np.mean(list(per_class.values())) == metrics["miou_pct"] and per_class["road"] > 80
    assert metrics["elev_error_cm"] < 3 and metrics["elev_mae_gt_cm"] < 5
    assert metrics["drive_s"] > 4.5 and metrics["rtf"] == metrics["drive_s"] / metrics["wall_s"]
    assert metrics["inputs"]["keyframes"] > 0 and metrics["lidar_supervision"] is True
    grid = np.load(out / "bev_elevation.npy")
    assert np.isfinite(grid).sum() > 1000
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.faces) > 1000
    assert (out / "config.yaml").read_text().startswith("vehicle:")
    assert (out / "checkpoint.pt").stat().st_size > 0 and (out / "bev_semantics.png").stat().st_size > 0
    assert not undocumented_metrics(metrics) and not {"rtf_mapping", "realtime_factor"} & set(metrics)
    # the map on the earth: bev.json's origin is the drive's, and a mapped cell of the GeoTIFF lands at its lat/lon
    origin = np.load(city_drive.with_name("city.gt.npz"))["enu_origin_lat_lon_alt"].tolist()
    bev = json.loads((out / "bev.json").read_text())
    assert bev["origin_lat_lon_alt"] == origin and bev["crs"].startswith("+proj=tmerc")
    i, j = np.argwhere(np.isfinite(grid))[0]
    x, y = bev["origin_xy"][0] + j * bev["resolution_m"], bev["origin_xy"][1] + i * bev["resolution_m"]
    with rasterio.open(out / "bev_elevation.tif") as tif:
        assert tif.read(1)[tif.index(x, y)] == grid[i, j]
        (lon,), (lat,) = transform(tif.crs, "EPSG:4326", [x], [y])
    frame = LocalFrame(*origin)
    placed = frame.geodetic_to_enu(lat, lon, frame.alt_m + grid[i, j])
    assert np.hypot(placed[0] - x, placed[1] - y) < 1e-3  # metres


def undocumented_metrics(metrics: dict) -> set[str]:
    """The keys of a metrics.json (and of its `inputs`, as inputs.KEY) that docs/map-outputs.md's table lacks."""
    documented = set(re.findall(r"^\| `([a-z0-9_.]+)` \|", (REPO / "docs" / "map-outputs.md").read_text(), re.M))
    return (set(metrics) | {f"inputs.{k}" for k in metrics.get("inputs", {})}) - documented


def _reconstruct(logs, out, *extra):
    return subprocess.run([sys.executable, "-m", "daemon.commands.cli", "reconstruct", *map(str, logs),
                           "--out", str(out), *extra], cwd=REPO, capture_output=True, text=True, timeout=600)


def test_a_drive_without_masks_maps_colour_and_elevation_and_says_semantics_are_unavailable(
        city_drive_without_masks, tmp_path):
    out = tmp_path / "map"
    run = _reconstruct([city_drive_without_masks], out, "--gt", city_drive_without_masks.with_name("city.gt.npz"))
    assert run.returncode == 0, run.stderr[-3000:]
    frames = 150  # 3 cameras x 5 s x 10 Hz
    assert ("roadlog reconstruct: warning: 150 of 150 camera frames have no semantic mask and no segmentation "
            "model is configured (mapper.segmentation.provider: log)") in run.stderr
    printed = json.loads(run.stdout.strip().splitlines()[-1])
    metrics = json.loads((out / "metrics.json").read_text())
    assert printed["miou_pct"] is None and metrics["miou_pct"] is None and metrics["iou_pct"] is None
    assert metrics["semantics"] == printed["semantics"]
    assert metrics["semantics"].startswith(f"unavailable: {metrics['keyframes_train']} of "
                                           f"{metrics['keyframes_train']} training keyframes have no mask")
    assert metrics["inputs"]["frames"] == frames and metrics["inputs"]["frames_without_mask"] == frames
    assert metrics["inputs"]["keyframes_without_mask"] == metrics["inputs"]["keyframes"] > 20
    assert metrics["psnr_pixels"].startswith("mapped surface") and metrics["psnr_db"] > 15
    # what stands on the road in view (parked and oncoming cars, the lead car) is left out by the Lidar's test
    assert metrics["maskless_rejection"].startswith("lidar occlusion") and metrics["maskless_views_unchecked"] == 0
    assert 20 < metrics["maskless_hidden_pct"] < 80
    assert metrics["elev_error_cm"] < 3 and metrics["elev_mae_gt_cm"] < 5  # the Lidar's elevation, as with masks
    for name in ("bev_rgb_front_wide.png", "bev_rgb_front_left.png", "bev_rgb_front_right.png", "bev_elevation.png",
                 "bev_elevation.npy", "mesh.ply", "mesh.glb", "checkpoint.pt"):
        assert (out / name).stat().st_size > 0, name
    assert np.isfinite(np.load(out / "bev_elevation.npy")).sum() > 1000
    assert not list(out.glob("bev_semantics*")) and json.loads((out / "bev.json").read_text())["semantics"] is False
    assert not undocumented_metrics(metrics)  # the maskless_* keys too
    header = (out / "mesh.ply").read_bytes()[:1000].split(b"end_header")[0]
    assert b"property uchar red" in header and b"label" not in header  # no vertex labels either


def test_a_drive_with_some_masks_takes_semantics_from_those_frames(city_drive, tmp_path):
    """The front_left camera's masks are all missing and front_wide's after the drive's first half (a segmenter
    that stopped): every frame still maps, the semantics come from the frames with masks."""
    from daemon.log_format.reader import read_log
    from daemon.log_format.writer import LogWriter
    from daemon.spine.config import load_config

    records = list(read_log([city_drive]))
    middle = (records[0].log_time_ns + records[-1].log_time_ns) // 2
    dropped = {"mask/front_left"}
    mixed = tmp_path / "mixed.mcap"
    writer = LogWriter(mixed, load_config(REPO / "configs" / "sim.yaml"))
    left_out = 0
    for r in records:
        if r.topic in dropped or (r.topic == "mask/front_wide" and r.log_time_ns > middle):
            left_out += 1
            continue
        writer.write(r.topic, r.message)
    writer.close()
    out = tmp_path / "map"
    run = _reconstruct([mixed], out, "--config", REPO / "configs" / "sim.yaml",
                       "--gt", city_drive.with_name("city.gt.npz"))
    assert run.returncode == 0, run.stderr[-3000:]
    assert (f"warning: {left_out} of 150 camera frames have no semantic mask" in run.stderr
            and "semantics come from the frames with a mask only" in run.stderr), run.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["inputs"]["frames_without_mask"] == left_out > 60
    assert metrics["semantics"].startswith("partial: ") and metrics["keyframes_without_semantics"] > 20
    assert metrics["inputs"]["keyframes"] > 40  # as many as with every mask: none is dropped for want of one
    assert 40 < metrics["miou_pct"] <= 100 and metrics["iou_pct"]["road"] > 80
    labels = np.load(out / "bev_semantics.npy")
    mapped = np.isfinite(np.load(out / "bev_elevation.npy"))
    assert 0.3 < (labels[mapped] != 255).mean() <= 1.0


def test_a_log_recorded_with_mapper_keys_this_version_lacks_still_reconstructs(tmp_path, capsys):
    """A renamed or removed mapper key in a log's recorded config is dropped and named (today's default applies); a
    key unknown in the sensors still stops the read: it describes the data."""
    config = load_config(REPO / "configs" / "sim.yaml")
    data = yaml.safe_load(config_to_yaml(config))
    data["mapper"]["retired_knob"] = 3
    data["mapper"]["mesh"]["old_name_m"] = 0.4
    log = tmp_path / "old.mcap"
    with LogWriter(log, config, metadata={"config": yaml.safe_dump(data)}, config_path=REPO / "configs" / "sim.yaml"):
        pass
    read, _ = config_from_logs([str(log)])
    assert read.mapper == config.mapper and read.sensors == config.sensors
    err = capsys.readouterr().err
    assert "mapper.mesh.old_name_m, mapper.retired_knob" in err and "unknown to this version" in err
    data["sensors"]["cameras"][0]["lens_colour"] = "blue"
    with LogWriter(log, config, metadata={"config": yaml.safe_dump(data)}, config_path=REPO / "configs" / "sim.yaml"):
        pass
    with pytest.raises(ConfigError, match="lens_colour"):
        config_from_logs([str(log)])


def test_the_truth_moved_into_a_maps_frame_holds_the_same_heights_and_classes_at_the_same_places():
    """The live map's frame starts at the drive's first fix, not at the truth's origin: bench/live_vs_reconstruct
    scores both maps in it (the same map read 82.7 % mIoU in the truth's frame, 77.0 % in the live map's: where its
    10 cm cells fall against the truth's counts, so the two maps must share a frame)."""
    from mapping.method.scene_data import GroundTruth
    from mapping.offline.reconstruct_command import DriveTruth

    truth_frame = LocalFrame(48.137154, 11.576124, 520.0)
    h, w, res = 400, 600, 0.05
    ii, jj = np.mgrid[0:h, 0:w]
    elevation = (0.02 * jj * res + 0.01 * ii * res).astype(np.float32)
    semantic = ((jj // 3) % 4).astype(np.uint8)  # stripes 15 cm wide
    truth = DriveTruth(truth_frame, GroundTruth(elevation, (-10.0, -5.0), res, semantic),
                       np.array([[1.0, 2.0, 0.3]]))
    map_frame = LocalFrame(*(float(v[0]) for v in truth_frame.enu_to_geodetic(np.array([[20.6255, -6.1563, 1.8046]]))))
    moved = truth.in_frame(map_frame)
    assert moved.origin == map_frame and truth.in_frame(truth_frame) is truth
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, h, 200), rng.integers(0, w, 200)
    at = np.stack([-10.0 + cols * res, -5.0 + rows * res, elevation[rows, cols]], 1)  # cell centres, truth frame
    there = map_frame.geodetic_to_enu(*truth_frame.enu_to_geodetic(at))  # the same places in the map's frame
    gt = moved.elevation
    j = np.round((there[:, 0] - gt.origin_xy[0]) / res).astype(int)
    i = np.round((there[:, 1] - gt.origin_xy[1]) / res).astype(int)
    assert np.array_equal(gt.semantic[i, j], semantic[rows, cols])
    assert np.abs(gt.elevation_m[i, j] - there[:, 2]).max() < 1e-3
    assert np.abs(moved.lidar_points - map_frame.geodetic_to_enu(*truth_frame.enu_to_geodetic(
        truth.lidar_points))).max() < 1e-3
    far = LocalFrame(*(float(v[0]) for v in truth_frame.enu_to_geodetic(np.array([[5000.0, 0.0, 0.0]]))))
    with pytest.raises(ValueError, match="too far apart"):
        truth.in_frame(far)
