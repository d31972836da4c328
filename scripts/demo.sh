#!/usr/bin/env bash
# Installs roadlog, then runs the demo on the built-in simulated drive.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install.sh
exec .venv/bin/roadlog demo "$@"
