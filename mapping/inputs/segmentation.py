"""The ONNX segmentation provider: a semantic-segmentation model run with onnxruntime on keyframe images,
its classes mapped to the road map's (daemon.spine.config.SegmentationConfig says what the model must take and
give). Masks recorded in the log need none of this (provider `log`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from daemon.spine.config import ConfigError
from daemon.spine.mapper_config import SegmentationConfig
from daemon.spine.semantic_classes import SemanticClass

UNLABELLED = 255  # mask value of pixels no map class is given for (never used by a loss)


@dataclass
class OnnxSegmenter:
    """A loaded model: `labels(image)` gives the mask of an RGB image."""

    session: object  # onnxruntime.InferenceSession
    input_name: str
    input_size: tuple[int, int] | None  # (width, height) to resize to, None: the image's own
    mean: np.ndarray  # (3,) float32
    std: np.ndarray  # (3,) float32
    lut: np.ndarray  # (model classes,) uint8: map class id of each model class id

    @staticmethod
    def load(config: SegmentationConfig, config_file: str | Path | None = None) -> OnnxSegmenter:
        """The model of an `onnx` provider config (a relative model path is taken from the config file's
        folder); a missing or unreadable model is a ConfigError naming the file."""
        import onnxruntime

        path = Path(config.model).expanduser()
        if not path.is_absolute() and config_file is not None:
            path = Path(config_file).resolve().parent / path
        if not path.is_file():
            raise ConfigError(f"mapper.segmentation.model: {path} does not exist")
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = config.threads
        options.inter_op_num_threads = 1
        try:
            session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise ConfigError(f"mapper.segmentation.model: {path} is not a usable ONNX model ({exc})") from exc
        inputs = session.get_inputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise ConfigError(f"mapper.segmentation.model: {path} must take one (1, 3, H, W) image, takes "
                              f"{[(i.name, i.shape) for i in inputs]}")
        h, w = inputs[0].shape[2:]
        size = config.input_size or ((w, h) if isinstance(w, int) and isinstance(h, int) else None)
        lut = np.full(max(config.class_map) + 1, UNLABELLED, np.uint8)
        for model_class, name in config.class_map.items():
            lut[model_class] = SemanticClass[name.upper()]
        return OnnxSegmenter(session, inputs[0].name, size, np.array(config.mean, np.float32),
                             np.array(config.std, np.float32), lut)

    def labels(self, image: np.ndarray) -> np.ndarray:
        """(H, W) uint8 map class ids of an (H, W, 3) RGB uint8 image (UNLABELLED where the model's class is
        not in the class map), the model's output resized to the image (nearest)."""
        h, w = image.shape[:2]
        x = image if self.input_size is None else cv2.resize(image, self.input_size, interpolation=cv2.INTER_AREA)
        x = (x.astype(np.float32) / 255.0 - self.mean) / self.std
        (out,) = self.session.run(None, {self.input_name: np.ascontiguousarray(x.transpose(2, 0, 1)[None])})
        if out.ndim == 4:
            classes = out[0].argmax(0)
        elif out.ndim == 3:
            classes = out[0]
        else:
            raise ValueError(f"segmentation model output of shape {out.shape}: expected (1, C, H, W) scores or "
                             f"(1, H, W) class ids")
        classes = classes.astype(np.int64)
        known = (classes >= 0) & (classes < len(self.lut))
        mask = np.full(classes.shape, UNLABELLED, np.uint8)
        mask[known] = self.lut[classes[known]]
        if mask.shape != (h, w):
            mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_NEAREST)
        return mask
