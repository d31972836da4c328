"""The semantic classes of the road map (the paper's five) and the mask-only obstacle label."""

from enum import IntEnum

import numpy as np


class SemanticClass(IntEnum):
    """Class ids as stored in segmentation masks, map rasters and mesh vertex labels."""

    ROAD = 0
    LANE_MARKING = 1
    CURB = 2
    MANHOLE = 3
    BACKGROUND = 4
    OBSTACLE = 5  # masks only (cars, pedestrians): never a map class, excluded from every loss


MAP_CLASSES = (
    SemanticClass.ROAD,
    SemanticClass.LANE_MARKING,
    SemanticClass.CURB,
    SemanticClass.MANHOLE,
    SemanticClass.BACKGROUND,
)
NUM_MAP_CLASSES = len(MAP_CLASSES)
ROAD_SURFACE_CLASSES = (
    SemanticClass.ROAD,
    SemanticClass.LANE_MARKING,
    SemanticClass.CURB,
    SemanticClass.MANHOLE,
)

# RGB colour of each class id for colourised maps (index = class id).
CLASS_COLOURS = np.array(
    [
        [128, 64, 128],  # road
        [255, 255, 255],  # lane marking
        [244, 35, 232],  # curb
        [255, 170, 0],  # manhole
        [70, 70, 70],  # background
        [0, 0, 142],  # obstacle
    ],
    dtype=np.uint8,
)
