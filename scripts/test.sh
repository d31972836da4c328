#!/usr/bin/env bash
# Installs what the tests need, then runs the default (fast) test suite; extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install.sh
exec .venv/bin/python -m pytest "$@"
