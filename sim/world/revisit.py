"""Another visit of the same world (`roadlog simulate --visit N`): the road, its paint and its trees as the world's
seed draws them, and from the visit's own seed everything a second drive changes: the traffic (other parked cars,
other moving ones), the ego car's speed and wander, every sensor's noise, the light (sun, ambient, exposure) and
a constant offset of the GNSS fixes (another day's RTK base: the whole drive's positions shifted a few cm to
decimetres), which a multi-drive map must estimate and take out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.world.scenarios import Scenario

GNSS_OFFSET_H_M = 0.25  # horizontal offset of a visit's fixes: uniform in a disc of this radius, m
GNSS_OFFSET_V_M = 0.10  # vertical: uniform in +-this, m


@dataclass(frozen=True)
class Visit:
    """What differs on visit `number` of a world (visit 0 is the plain drive: nothing differs)."""

    number: int
    drive_seed: int  # seeds the ego's motion, the traffic and the sensors' noise
    scenario: Scenario  # the world's scenario with this visit's light
    gnss_offset_enu_m: tuple[float, float, float]  # added to every true antenna position before it is reported


def visit(scenario: Scenario, world_seed: int, number: int) -> Visit:
    """Visit `number` (>= 0) of the world `scenario` draws from `world_seed`."""
    if number == 0:
        return Visit(0, world_seed, scenario, (0.0, 0.0, 0.0))
    rng = np.random.default_rng([world_seed, 100, number])
    drive_seed = int(rng.integers(2**31))
    light = scenario.lighting
    if light.mode == "day":
        light = light.model_copy(update={
            "sun_azimuth_deg": float((light.sun_azimuth_deg + rng.uniform(-90, 90)) % 360),
            "sun_elevation_deg": float(np.clip(light.sun_elevation_deg + rng.uniform(-20, 20), 15, 75)),
            "ambient": float(light.ambient * rng.uniform(0.8, 1.2)),
            "exposure": float(light.exposure * rng.uniform(0.85, 1.15))})
    radius, angle = GNSS_OFFSET_H_M * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
    offset = (float(radius * np.cos(angle)), float(radius * np.sin(angle)),
              float(rng.uniform(-GNSS_OFFSET_V_M, GNSS_OFFSET_V_M)))
    return Visit(number, drive_seed, scenario.model_copy(update={"lighting": light}), offset)
