"""The vendor decoders' compiled loops where numba cannot cache them: no writable cache folder at all, or one that
fails when the compiled code is written. Each case in a fresh process, decoding a real capture as this process does."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.velodyne_decoder import velodyne_decoder

ROOT = Path(__file__).resolve().parents[2]
NEBULA = Path("/work/shared/data/lidar_nebula")
CAPTURE, CALIBRATION = NEBULA / "velodyne" / "vlp32.pcap", NEBULA / "calib" / "VLP32.yaml"

_DECODE = """
import sys
import numpy as np
import numba.core.caching as caching
if sys.argv[1] == "no_folder":
    caching.CacheImpl._locator_classes = []  # numba finds no folder it may write
else:
    def refuse(self, key, data):
        raise PermissionError(13, "Permission denied", self._cache_path)
    caching.IndexDataCacheFile.save = refuse  # the folder is there, writing into it fails
from drivers.lidar.pcap_udp import read_pcap_udp
from drivers.lidar.velodyne_decoder import velodyne_decoder
payloads = [d.payload for d in read_pcap_udp(sys.argv[2]).datagrams][:100]
np.save(sys.argv[4], velodyne_decoder("velodyne-vlp32c", sys.argv[3]).decode(payloads).xyz)
"""


def _decode_in_a_process(case: str, tmp_path: Path) -> np.ndarray:
    out = tmp_path / f"{case}.npy"
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    result = subprocess.run([sys.executable, "-c", _DECODE, case, str(CAPTURE), str(CALIBRATION), str(out)],
                            env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return np.load(out)


def _expected() -> np.ndarray:
    payloads = [d.payload for d in read_pcap_udp(CAPTURE).datagrams][:100]
    return velodyne_decoder("velodyne-vlp32c", CALIBRATION).decode(payloads).xyz


def test_a_decoder_works_where_numba_finds_no_cache_folder(tmp_path):
    xyz = _decode_in_a_process("no_folder", tmp_path)
    assert len(xyz) > 10_000
    np.testing.assert_array_equal(xyz, _expected())


@pytest.mark.slow
def test_a_decoder_works_where_writing_the_cache_fails(tmp_path):
    xyz = _decode_in_a_process("write_fails", tmp_path)
    assert not list((tmp_path / "cache").rglob("*.nbc"))  # nothing was cached
    np.testing.assert_array_equal(xyz, _expected())
