"""A segmentation network's mask for a rendered frame: the true labels with the errors such a network
makes (wobbly boundaries, thin far markings lost, blobs and pixels of the wrong class), as a PNG of ids."""

from __future__ import annotations

import cv2
import numpy as np

from daemon.spine.semantic_classes import SemanticClass

BOUNDARY_WOBBLE_PX = 1.2
FAR_MARKING_M = 30.0
BLOBS_PER_FRAME = 5.0
PIXEL_ERROR_RATE = 0.002
# What each true class is mistaken for.
CONFUSION = {
    SemanticClass.ROAD: (SemanticClass.LANE_MARKING, SemanticClass.MANHOLE, SemanticClass.BACKGROUND),
    SemanticClass.LANE_MARKING: (SemanticClass.ROAD,),
    SemanticClass.CURB: (SemanticClass.ROAD, SemanticClass.BACKGROUND),
    SemanticClass.MANHOLE: (SemanticClass.ROAD,),
    SemanticClass.BACKGROUND: (SemanticClass.CURB, SemanticClass.ROAD),
    SemanticClass.OBSTACLE: (SemanticClass.BACKGROUND, SemanticClass.ROAD),
}


def segmentation_mask(labels: np.ndarray, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W) uint8 class ids as a segmentation network would give them for the true `labels`."""
    h, w = labels.shape
    out = labels.copy()
    far = (out == SemanticClass.LANE_MARKING) & (depth > FAR_MARKING_M)
    lost = rng.random(int(far.sum()), dtype=np.float32) < np.clip((depth[far] - FAR_MARKING_M) / 50.0, 0, 0.8)
    out[np.flatnonzero(far.ravel())[lost] // w, np.flatnonzero(far.ravel())[lost] % w] = SemanticClass.ROAD
    coarse = rng.standard_normal((h // 24 + 2, w // 24 + 2, 2), dtype=np.float32) * BOUNDARY_WOBBLE_PX
    shift = cv2.resize(coarse, ((w // 24 + 2) * 24, (h // 24 + 2) * 24), interpolation=cv2.INTER_LINEAR)[:h, :w]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    out = cv2.remap(out, gx + shift[..., 0], gy + shift[..., 1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    for _ in range(rng.poisson(BLOBS_PER_FRAME)):
        x, y = int(rng.integers(w)), int(rng.integers(h // 3, h))
        wrong = CONFUSION[SemanticClass(int(out[y, x]))]
        axes = (int(rng.integers(2, 14)), int(rng.integers(2, 8)))
        cv2.ellipse(out, (x, y), axes, float(rng.uniform(0, 180)), 0, 360, int(wrong[rng.integers(len(wrong))]), -1)
    n = rng.binomial(h * w, PIXEL_ERROR_RATE)
    flat = out.reshape(-1)
    flat[rng.integers(0, h * w, n)] = rng.integers(0, 5, n)
    return out


def encode_mask_png(mask: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", mask, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()
