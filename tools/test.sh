#!/usr/bin/env bash
# Sets up and runs the whole test suite. `.ci/run` calls exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
bash tools/ci_system_deps.sh   # iproute2 (network namespaces), headless MAVProxy
exec .venv/bin/python -m pytest "$@"
