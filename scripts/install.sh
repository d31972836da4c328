#!/usr/bin/env bash
# Creates .venv (Python 3.11) and installs roadlog with its test extras. torch is pinned to the CPU
# build 2.13.0 first: an unpinned torch would pull gigabytes of CUDA wheels. Where npm is, the Khronos glTF
# validator goes into tests/.node (tests/mapping/test_map_files.py checks the map's GLB with it; skipped without).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$(command -v python3.11 || command -v python3)}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q torch==2.13.0
.venv/bin/python -m pip install -q -e '.[test]'
if command -v npm >/dev/null; then
  npm install -s --no-audit --no-fund --prefix tests/.node gltf-validator@2.0.0-dev.3.10 \
    || echo "install.sh: npm could not install gltf-validator; its test will be skipped" >&2
fi
