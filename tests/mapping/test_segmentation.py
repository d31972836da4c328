"""The ONNX segmentation provider, with a tiny model the test builds itself: a 1x1 convolution that
classes pixels by colour (dark: road, bright: lane marking, red: obstacle, blue: a class the map has not)."""

from pathlib import Path

import numpy as np
import onnx
import pytest
import yaml
from onnx import TensorProto, helper, numpy_helper

from daemon.spine.config import ConfigError, load_config
from daemon.spine.mapper_config import SegmentationConfig
from daemon.spine.semantic_classes import SemanticClass
from mapping.inputs.drive_inputs import load_drive
from mapping.inputs.segmentation import UNLABELLED, OnnxSegmenter
from mapping.offline.reconstruct_command import main as reconstruct_main
from tests.daemon_fixtures import private_config

CLASS_MAP = {0: "road", 1: "lane_marking", 2: "obstacle"}  # model class 3 (blue) is left out


def _colour_model(path: Path, height: int | str = "H", width: int | str = "W") -> Path:
    """(1, 3, H, W) image in [0, 1] -> (1, 4, H, W) class scores."""
    weight = np.array([[-1, -1, -1], [1, 1, 1], [4, -4, -4], [-4, -4, 4]], np.float32).reshape(4, 3, 1, 1)
    bias = np.array([1.5, -1.5, -0.5, -0.5], np.float32)
    graph = helper.make_graph(
        [helper.make_node("Conv", ["image", "weight", "bias"], ["scores"])], "colour_classes",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, height, width])],
        [helper.make_tensor_value_info("scores", TensorProto.FLOAT, [1, 4, height, width])],
        [numpy_helper.from_array(weight, "weight"), numpy_helper.from_array(bias, "bias")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def _quadrants(h: int, w: int) -> np.ndarray:
    image = np.zeros((h, w, 3), np.uint8)
    image[: h // 2, : w // 2] = 60  # dark grey
    image[: h // 2, w // 2:] = 250  # white
    image[h // 2:, : w // 2] = [220, 20, 20]  # red
    image[h // 2:, w // 2:] = [20, 20, 220]  # blue
    return image


def test_the_model_labels_each_pixel_with_the_mapped_class(tmp_path):
    seg = OnnxSegmenter.load(SegmentationConfig(provider="onnx", model=str(_colour_model(tmp_path / "m.onnx")),
                                                class_map=CLASS_MAP))
    labels = seg.labels(_quadrants(30, 40))
    assert labels.shape == (30, 40) and labels.dtype == np.uint8
    assert (labels[:15, :20] == SemanticClass.ROAD).all()
    assert (labels[:15, 20:] == SemanticClass.LANE_MARKING).all()
    assert (labels[15:, :20] == SemanticClass.OBSTACLE).all()
    assert (labels[15:, 20:] == UNLABELLED).all()


def test_a_fixed_size_model_gets_a_resized_image_and_its_labels_are_resized_back(tmp_path):
    model = _colour_model(tmp_path / "m.onnx", height=6, width=8)
    seg = OnnxSegmenter.load(SegmentationConfig(provider="onnx", model="m.onnx", class_map=CLASS_MAP),
                             config_file=tmp_path / "car.yaml")  # a relative model path: from the config's folder
    assert model.exists() and seg.input_size == (8, 6)
    labels = seg.labels(_quadrants(60, 80))
    assert labels.shape == (60, 80)
    assert (labels[:30, :40] == SemanticClass.ROAD).all() and (labels[30:, 40:] == UNLABELLED).all()


def test_a_missing_or_broken_model_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        OnnxSegmenter.load(SegmentationConfig(provider="onnx", model=str(tmp_path / "none.onnx"), class_map=CLASS_MAP))
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    with pytest.raises(ConfigError, match="not a usable ONNX model"):
        OnnxSegmenter.load(SegmentationConfig(provider="onnx", model=str(tmp_path / "bad.onnx"), class_map=CLASS_MAP))
    with pytest.raises(ValueError, match="needs `model`"):
        SegmentationConfig(provider="onnx")


def _onnx_config(tmp_path: Path, model: Path) -> Path:
    _, path = private_config(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["mapper"]["segmentation"] = {"provider": "onnx", "model": str(model), "class_map": CLASS_MAP}
    path.write_text(yaml.safe_dump(data))
    return path


def test_keyframes_of_a_recorded_drive_take_their_semantics_from_the_model(tmp_path, city_drive):
    path = _onnx_config(tmp_path, _colour_model(tmp_path / "m.onnx"))
    config = load_config(path)
    drive = load_drive([city_drive], config, path, use_lidar=False)
    assert len(drive.keyframes) > 5 and drive.counts["frames_without_mask"] == 0
    seg = OnnxSegmenter.load(config.mapper.segmentation, path)
    for kf in drive.keyframes[:: max(1, len(drive.keyframes) // 4)]:
        assert np.array_equal(kf.semantics, seg.labels(kf.image))
    classes = np.unique(np.concatenate([kf.semantics.ravel() for kf in drive.keyframes]))
    assert SemanticClass.ROAD in classes and set(classes.tolist()) <= {0, 1, 5, UNLABELLED}


def test_reconstruct_with_a_missing_model_exits_with_a_config_error(tmp_path, city_drive, capsys):
    path = _onnx_config(tmp_path, tmp_path / "missing.onnx")
    assert reconstruct_main([str(city_drive), "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    assert "missing.onnx does not exist" in capsys.readouterr().err
    assert not (tmp_path / "out" / "metrics.json").exists()
