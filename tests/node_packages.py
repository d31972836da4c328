"""The npm packages the tests' independent readers run on node (tests/.node/node_modules): installed from npm when
missing; a test that needs them is skipped, with the reason, where node or npm is absent or the install fails."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

NODE_DIR = Path(__file__).resolve().parent / ".node"
INSTALL_TIMEOUT_S = 180


def node_modules(*packages: str) -> Path:
    """tests/.node/node_modules holding every package (npm specs, "name@range"), the missing ones installed."""
    modules = NODE_DIR / "node_modules"
    names = [spec.rsplit("@", 1)[0] if spec.rfind("@") > 0 else spec for spec in packages]
    if all((modules / name).is_dir() for name in names):
        return modules
    what = " and ".join(names)
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip(f"node and npm are not installed: {what} cannot run")
    NODE_DIR.mkdir(parents=True, exist_ok=True)
    try:
        done = subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--loglevel=error", "--prefix",
                               str(NODE_DIR), *packages], capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.skip(f"npm install of {what} took over {INSTALL_TIMEOUT_S} s (no registry?)")
    if done.returncode != 0:
        pytest.skip(f"npm install of {what} failed: {done.stderr.strip()[-300:]}")
    return modules
