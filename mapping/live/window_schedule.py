"""The live worker's window schedule: windows of `before_m` + `after_m` metres along the drive, centres every half
window (so they overlap by half), and how many a drive has ended or needs. Pure functions of distances."""

from __future__ import annotations


def window_span(index: int, before_m: float, after_m: float) -> tuple[float, float, float]:
    """(centre, start, end) in metres along the drive of window `index` (centres every half window)."""
    centre = index * (before_m + after_m) / 2.0
    return centre, max(0.0, centre - before_m), centre + after_m


def windows_for_drive(total_m: float, before_m: float, after_m: float) -> int:
    """How many windows a finished drive of `total_m` needs: every centre whose central stretch has road."""
    half = (before_m + after_m) / 4.0
    k = 0
    while window_span(k, before_m, after_m)[0] - half < total_m:
        k += 1
    return max(k, 1)


def windows_ended(first: int, distance_m: float, before_m: float, after_m: float) -> int:
    """How many windows from `first` on end within the `distance_m` driven so far."""
    ended = 0
    while window_span(first + ended, before_m, after_m)[2] <= distance_m:
        ended += 1
    return ended
