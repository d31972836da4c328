"""Lane markings kept where the views blur them.

A lane marking is a line 10-30 cm wide: one to three mesh sides. Every view smears it: the segmenter's boundaries
wobble by a pixel or so, and beside the car a pixel covers more ground along its line of sight than the marking is
wide (30 cm at 13 m for a 400 px focal length 1.4 m up). Averaged over the views, a thin line's label frequency at its
centre falls below the road's around it, and the map's argmax loses the line, though the centre stays a ridge of
lane frequency across the line. A vertex whose lane frequency exceeds both its neighbours on opposite sides along
some lattice direction is on such a ridge; its lane frequency is raised by `gain` times the smaller of the two
excesses and its frequencies are normalised again. The edges of a wide marking (higher on one side, lower on the
other) and the inside of a uniform area are not ridges and keep their frequencies. A thin line that runs along
the mesh's rows centred between two of them has no centre vertex and gains nothing: the two rules tried for that
case widened lines the plain frequencies mapped (bench/RESULTS.md, 2026-12-08).
"""

from __future__ import annotations

import numpy as np

OPPOSITE_NEIGHBOURS = ((0, 1), (2, 5), (3, 4))  # road_mesh's neighbour slots facing each other through the vertex:
# left / right, lower left / upper right, lower right / upper left


def line_centre_excess(frequency: np.ndarray, neighbours: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(N,) how far each vertex's `frequency` (N,) exceeds both its neighbours on opposite sides, along the lattice
    direction where that is largest; 0 where no direction has both neighbours `known` (N,) and lower."""
    present = neighbours >= 0
    present[present] = known[neighbours[present]]
    around = np.where(present, frequency[np.maximum(neighbours, 0)], np.inf)  # a missing side is never lower
    excess = np.zeros(len(frequency))
    for a, b in OPPOSITE_NEIGHBOURS:
        excess = np.maximum(excess, frequency - np.maximum(around[:, a], around[:, b]))
    return np.where(known, excess, 0.0)


def raise_line_centres(frequencies: np.ndarray, neighbours: np.ndarray, known: np.ndarray, line_class: int,
                       gain: float) -> np.ndarray:
    """(N, C) label frequencies with `line_class`'s raised on its line centres (line_centre_excess times `gain`) and
    each row normalised again. `frequencies`: (N, C) rows summing to 1 where `known`; `neighbours`: (N, 6) the
    mesh's (-1: none)."""
    if gain <= 0:
        return frequencies
    excess = line_centre_excess(frequencies[:, line_class], neighbours, known)
    ridge = np.flatnonzero(excess > 0)
    out = frequencies.copy()
    out[ridge, line_class] += gain * excess[ridge]
    out[ridge] /= out[ridge].sum(1, keepdims=True)
    return out
