"""bench/parser_fuzz.py's mutations, a few hundred of them in the default suite (the bench runs thousands): mutated
Ouster metadata through the Lidar driver's start-up check raises nothing but ValueError, mutated car configs through
load_config and every start-up check of check-config nothing but ConfigError, mutated real Ouster packets, u-blox
streams and CAN frames through the drivers' decoding nothing at all, with every packet, byte and frame accounted
for, and no case hangs. The MCAP reader and recovery have their own fuzz test (tests/daemon/test_log_damage.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def parser_fuzz():
    spec = importlib.util.spec_from_file_location("parser_fuzz", REPO / "bench" / "parser_fuzz.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("parser, cases", [("ouster_metadata", 300), ("config", 120)])
def test_fuzzed_metadata_and_configs_raise_only_their_own_errors(parser_fuzz, parser, cases):
    result = parser_fuzz.run([parser], cases, seed=7)[parser]
    assert result["uncaught"] == 0 and result["hangs"] == 0, result.get("examples")
    assert result["cases"] == cases and len(result["outcomes"]) > 1  # some accepted, some refused


@pytest.mark.skipif(not Path("/work/shared/data/ouster").is_dir(), reason="shared sensor data not present")
@pytest.mark.parametrize("parser, tally", [("ouster_packets", "counts_inconsistent"), ("nmea_ubx", "bytes_unaccounted"),
                                           ("can", "frames_not_published")])
def test_fuzzed_sensor_streams_raise_nothing_and_lose_nothing(parser_fuzz, parser, tally):
    result = parser_fuzz.run([parser], 300, seed=7)[parser]
    assert result["uncaught"] == 0 and result["hangs"] == 0, result.get("examples")
    assert result[tally] == 0 and result.get("bad_published", 0) == 0
    assert result["cases"] == 300 and len(result["outcomes"]) > 1  # the mutations reach both outcomes
