#!/usr/bin/env bash
# Sets up and runs the daemon on the built-in simulated field, printing its state as it drives.
# Extra arguments go to `fieldguard run` (e.g. --duration 300, or --sim stubble-night).
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
if [ $# -eq 0 ]; then set -- --sim --duration 60; fi
echo "fieldguard: web console (read-only) at http://127.0.0.1:8080/ while it runs (docs/console.md)"
exec .venv/bin/fieldguard run --print-every 2 "$@"
