"""Shared fixtures: one short simulated city drive per test session (it costs tens of seconds to make)."""

from pathlib import Path

import pytest

from daemon.spine.config import load_config
from sim.drive_log import simulate_drive

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def city_drive(tmp_path_factory) -> Path:
    """A 5 s simulated city drive (seed 3): PATH.mcap, with PATH.gt.npz beside it."""
    out = tmp_path_factory.mktemp("city_drive") / "city.mcap"
    simulate_drive("city", 5.0, out, load_config(REPO / "configs" / "sim.yaml"), seed=3)
    return out


@pytest.fixture(scope="session")
def city_drive_without_masks(tmp_path_factory) -> Path:
    """The same drive as city_drive, logged without its mask topics (a car without a segmenter)."""
    out = tmp_path_factory.mktemp("city_drive_without_masks") / "city.mcap"
    simulate_drive("city", 5.0, out, load_config(REPO / "configs" / "sim.yaml"), seed=3, masks=False)
    return out
