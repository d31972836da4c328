"""The car config: shipped configs load; bad configs fail with one message naming file, key and expectation."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.commands.check_config import main as check_config_main
from daemon.processes.daemon_main import run_main
from daemon.processes.replay import replayed_topics
from daemon.spine.config import ConfigError, load_config, parse_config
from daemon.spine.mapper_config import MapperConfig
from daemon.spine.messages import PointCloud
from daemon.spine.point_cloud_codec import pack_points
from daemon.spine.process_table import process_table, required_drivers
from daemon.spine.recorded_config import sectioned_recorded_config
from daemon.spine.topics import LIDAR_IMU, LIDAR_PACKETS, LIDAR_POINTS, topic_table
from tests.daemon_fixtures import private_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("name", ["car.yaml", "sim.yaml"])
def test_shipped_configs_load(name):
    config = load_config(CONFIGS / name)
    assert [c.name for c in config.sensors.cameras] == ["front_wide", "front_left", "front_right"]
    assert config.mapper.faithful_fit.learning_rates.elevation_mlp == 0.01


def test_mapper_sections_default_to_what_the_fits_used_and_are_set_from_yaml(tmp_path):
    """configs/sim.yaml states the defaults; a fast-fit key in the YAML reaches the config."""
    assert load_config(CONFIGS / "sim.yaml").mapper == MapperConfig()
    path = _write_bad(tmp_path, lambda d: d["mapper"]["fast_fit"].update(lidar_detail_passes=0))
    assert load_config(path).mapper.fast_fit.lidar_detail_passes == 0


def test_car_config_matches_the_paper_car():
    config = load_config(CONFIGS / "car.yaml")
    sizes = [(c.width, c.height) for c in config.sensors.cameras]
    assert sizes == [(3840, 2160), (1920, 1080), (1920, 1080)]
    assert config.sensors.lidar.model == "ouster-os-128"
    assert config.status.bind_address == "127.0.0.1"


def _write_bad(tmp_path, mutate) -> Path:
    data = yaml.safe_load((CONFIGS / "sim.yaml").read_text())
    mutate(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    "mutate, key_path, expectation",
    [
        (lambda d: d["sensors"]["cameras"][0].update(width=-5), "sensors.cameras.0.width", "greater than 0"),
        (lambda d: d["sensors"]["cameras"][1].pop("intrinsics"), "sensors.cameras.1.intrinsics", "missing"),
        (lambda d: d["sensors"]["lidar"].update(port=70000), "sensors.lidar.port", "less than or equal"),
        (lambda d: d["mapper"]["faithful_fit"].update(epochs="many"), "mapper.faithful_fit.epochs", "valid integer"),
        (lambda d: d["mapper"].update(window_before_m=80.0), "mapper.window_before_m", "unknown key"),
        (lambda d: d["mapper"]["fast_fit"].update(ahead_m=0), "mapper.fast_fit.ahead_m", "greater than 0"),
        (lambda d: d["mapper"]["fast_fit"].update(label_footprint_subdivision=0),
         "mapper.fast_fit.label_footprint_subdivision", "greater than or equal to 1"),
        (lambda d: d["mapper"]["fast_fit"].update(lane_line_gain=-1.0), "mapper.fast_fit.lane_line_gain",
         "greater than or equal to 0"),
        (lambda d: d["recorder"].update(segment_secnds=5), "recorder.segment_secnds", "unknown key"),
        (lambda d: d["recorder"].update(deletion_hold_off_s=[60, 10]), "recorder.deletion_hold_off_s", "longer than"),
        (lambda d: d["recorder"].update(deletion_hold_off_s=[0, 10]), "recorder.deletion_hold_off_s.0",
         "greater than 0"),
        (lambda d: d["sensors"]["can"]["signals"].update(wheel_speed_fl="NOSIGNAL"),
         "sensors.can.signals.wheel_speed_fl", "MESSAGE.SIGNAL"),
        (lambda d: d["sensors"]["cameras"][2].update(name="front_left"), "sensors.cameras", "unique"),
        (lambda d: d["sensors"]["cameras"][0].update(backend="firewire"), "sensors.cameras.0.backend", "sim"),
        (lambda d: d["status"].update(bind_address=None), "status.bind_address", "valid string"),
    ],
)
def test_bad_config_names_file_key_and_expectation(tmp_path, mutate, key_path, expectation):
    path = _write_bad(tmp_path, mutate)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    message = str(err.value)
    assert str(path) in message
    assert key_path in message
    assert expectation in message


def test_not_yaml_and_missing_file(tmp_path):
    bad = tmp_path / "broken.yaml"
    bad.write_text("sensors: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    bad.write_bytes(b"sensors:\n  cameras: []\n\x05\n")  # a control character: the YAML reader refuses it at once
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config(tmp_path / "missing.yaml")
    scalar = tmp_path / "scalar.yaml"
    scalar.write_text("42\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_config(scalar)


def test_check_config_command_exit_codes(tmp_path, capsys):
    assert check_config_main([str(CONFIGS / "sim.yaml"), "--quiet"]) == 0
    bad = _write_bad(tmp_path, lambda d: d["mapper"]["faithful_fit"].update(batch_size=0))
    assert check_config_main([str(bad)]) == 2
    assert "mapper.faithful_fit.batch_size" in capsys.readouterr().err


def test_a_config_recorded_before_the_mapper_was_sectioned_still_reads():
    """Logs recorded before the re-layout hold a flat mapper section: reconstruct reads them as they were."""
    data = yaml.safe_load((CONFIGS / "sim.yaml").read_text())
    data["mapper"] = {"enabled": True, "mesh_side_m": 0.2, "corridor_half_width_m": 12.0, "window_before_m": 60.0,
                      "window_after_m": 70.0, "colour_code_dim": 16, "seed": 4, "epochs": 3, "batch_size": 4,
                      "learning_rates": {"semantics": 0.2}, "keyframe_spacing_m": 2.0, "threads": 1,
                      "live_view": {"enabled": False}}
    with pytest.raises(ConfigError, match="mesh_side_m"):
        parse_config(data)
    m = parse_config(sectioned_recorded_config(data)).mapper
    assert (m.mesh.side_m, m.mesh.corridor_half_width_m, m.windows.before_m, m.windows.after_m) == (0.2, 12, 60, 70)
    assert (m.model.colour_code_dim, m.model.seed, m.inputs.keyframe_spacing_m) == (16, 4, 2.0)
    assert (m.faithful_fit.epochs, m.faithful_fit.batch_size, m.faithful_fit.learning_rates.semantics) == (3, 4, 0.2)
    assert m.runtime.torch_threads_faithful_fit == 1 and m.fast_fit == MapperConfig().fast_fit
    current = yaml.safe_load((CONFIGS / "sim.yaml").read_text())
    assert sectioned_recorded_config(current) == current  # a sectioned config passes unchanged


def _runnable(tmp_path, mutate) -> Path:
    """sim.yaml in tmp_path with its files named absolutely, then `mutate`d."""
    data = yaml.safe_load((CONFIGS / "sim.yaml").read_text())
    data["sensors"]["can"]["dbc_file"] = str(CONFIGS / "sim_car.dbc")
    data["sensors"]["lidar"]["metadata_file"] = str(CONFIGS / "sim_os128_metadata.json")
    mutate(data)
    path = tmp_path / "car.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_wheel_speeds_in_rad_s_pass_check_config(tmp_path, capsys):
    """speed_unit rad/s (a wheel's angular rate, times wheel_radius_m) is a unit the CAN driver takes (it raised
    KeyError: 'rad/s' in check-config and in the driver)."""
    config = _runnable(tmp_path, lambda d: d["sensors"]["can"]["signals"].update(speed_unit="rad/s"))
    assert check_config_main([str(config), "--quiet"]) == 0, capsys.readouterr().err


def _metadata(change) -> dict:
    doc = json.loads((CONFIGS / "sim_os128_metadata.json").read_text())
    change(doc)
    return doc


@pytest.mark.parametrize("doc, expected", [
    (_metadata(lambda d: d.update(lidar_data_format=[])), "lidar_data_format must be an object"),  # AttributeError
    (_metadata(lambda d: d["lidar_data_format"].update(column_window=[0])), "column_window"),  # IndexError
    (_metadata(lambda d: d["lidar_data_format"].update(columns_per_packet=0)), "columns_per_packet"),  # ZeroDivision
    (_metadata(lambda d: d["lidar_data_format"].update(pixel_shift_by_row=None)), "pixel_shift_by_row"),  # TypeError
    (_metadata(lambda d: d["beam_intrinsics"].update(beam_altitude_angles=["up"] * 128)), "beam_altitude_angles"),
    (_metadata(lambda d: d["config_params"].update(lidar_mode="1024")), "lidar_mode"),  # IndexError in the driver
    (_metadata(lambda d: d["config_params"].update(udp_port_lidar=70000)), "udp_port_lidar"),
    ([1, 2, 3], "the document must be an object"),
    ("[" * 100_000, "JSON nested too deeply"),  # RecursionError
    ("{\"lidar_data_format\": ", "not JSON"),
])
def test_broken_lidar_metadata_is_one_config_error_line(tmp_path, capsys, doc, expected):
    """Mutated Ouster metadata files raised TypeError/AttributeError/IndexError/ZeroDivisionError from check-config
    (or, for lidar_mode, from the driver right after its start-up check): now the parser names the key."""
    (tmp_path / "meta.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))
    config = _runnable(tmp_path, lambda d: d["sensors"]["lidar"].update(metadata_file=str(tmp_path / "meta.json")))
    assert check_config_main([str(config), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "lidar: " in err and "sensors.lidar.metadata_file" in err and expected in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    "mutate, names",
    [
        (lambda d: d["sensors"]["can"].update(dbc_file="absent.dbc"), ["can:", "absent.dbc"]),
        (lambda d: d["sensors"]["can"]["signals"].update(wheel_speed_fl="WHEEL_SPEEDS.NO_SUCH_SIGNAL"),
         ["can:", "NO_SUCH_SIGNAL"]),
        (lambda d: d["sensors"]["can"]["signals"].update(speed_unit="furlong/s"), ["sensors.can.signals.speed_unit"]),
        (lambda d: d["sensors"]["lidar"].update(metadata_file="junk.json"), ["lidar:", "mapper:", "junk.json"]),
        (lambda d: d["mapper"].update(segmentation={"provider": "onnx", "model": "absent.onnx",
                                                    "class_map": {0: "road"}}), ["mapper:", "absent.onnx"]),
        (lambda d: [c.update(backend="recorded", encoding="png") for c in d["sensors"]["cameras"][1:]],
         ["camera_", "front_left, front_right", "no live driver"]),
    ],
)
def test_check_config_runs_the_start_up_checks_of_every_process(tmp_path, capsys, mutate, names):
    """A config that parses but that a process would refuse at start is refused by check-config too."""
    (tmp_path / "junk.json").write_text("{not json")
    assert check_config_main([str(_runnable(tmp_path, lambda d: None)), "--quiet"]) == 0
    assert check_config_main([str(_runnable(tmp_path, mutate)), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert all(name in err for name in names), err
    assert "Traceback" not in err


def test_a_point_cloud_lidar_needs_no_metadata_and_carries_points_instead_of_packets(tmp_path):
    """Model point-cloud: scans that come decoded (an imported dataset); only it goes without a metadata file."""
    path = _write_bad(tmp_path, lambda d: (d["sensors"]["lidar"].update(model="point-cloud"),
                                           d["sensors"]["lidar"].pop("metadata_file")))
    config = load_config(path)
    assert config.sensors.lidar.point_clouds and config.sensors.lidar.metadata_file is None
    topics = topic_table(config)
    assert topics[LIDAR_POINTS].message_type is PointCloud and topics[LIDAR_POINTS].source == "lidar"
    assert LIDAR_PACKETS not in topics and LIDAR_IMU not in topics
    assert topics[LIDAR_POINTS].ring_bytes >= 16 * 2_700_000  # a good many 128-beam scans of ~2.6 MB
    for model in ("ouster-os-128", "ouster-os-32"):
        path = _write_bad(tmp_path, lambda d, m=model: (d["sensors"]["lidar"].update(model=m),
                                                        d["sensors"]["lidar"].pop("metadata_file")))
        with pytest.raises(ConfigError, match=f"sensors.lidar: .*metadata_file is required for model {model}"):
            load_config(path)
    assert not load_config(CONFIGS / "sim.yaml").sensors.lidar.point_clouds


def test_run_and_check_config_refuse_a_point_cloud_lidar_that_replay_plays(tmp_path, capsys):
    """There is no live driver for a point-cloud Lidar: `roadlog run` and check-config refuse the config (exit 2,
    before any process or ring exists); a replay of its logs plays `lidar/points` in the driver's place."""
    config, path = private_config(tmp_path, point_clouds=True)
    assert run_main(["--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert "sensors.lidar.model 'point-cloud' has no live driver" in err and "roadlog replay" in err
    assert "Traceback" not in err
    assert not list(Path("/dev/shm").glob(f"{config.bus.shm_prefix}.*"))
    assert check_config_main([str(path), "--quiet"]) == 2
    assert "has no live driver" in capsys.readouterr().err
    replay = process_table(config, str(path), "replay", replay_logs=("a.mcap",))
    assert [p.name for p in replay][0] == "replay" and "lidar" not in [p.name for p in replay]
    assert "lidar" in required_drivers(config) and LIDAR_POINTS in replayed_topics(config)


def test_the_point_cloud_topic_declares_room_for_the_largest_scan(tmp_path):
    """The ring check sizes `lidar/points` by its largest message: a 128-beam, 2048-column, dual-return scan (it
    declared the 64 KB of the small messages, so the check could never catch a ring too small for it)."""
    config, _ = private_config(tmp_path, point_clouds=True)
    topic = topic_table(config)[LIDAR_POINTS]
    largest = len(pack_points(np.zeros((128 * 2048 * 2, 3), np.float32)))
    assert largest <= topic.max_message_bytes <= topic.ring_bytes // 2
