#!/usr/bin/env bash
# Sets up and runs the daemon on the built-in simulated field, printing its state as it drives.
# Extra arguments go to `fieldguard run` (e.g. --duration 300, or --sim stubble-night; --sim
# greenhouse runs the RGB-D pipeline). It ends after 60 s unless --duration says otherwise.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
if [ $# -eq 0 ]; then set -- --sim; fi
# the demo ends by itself: 60 s of driving unless the arguments say how long
case " $* " in *" --duration "*|*" --duration="*) ;; *) set -- "$@" --duration 60 ;; esac
echo "fieldguard: web console (read-only) at http://127.0.0.1:8080/ while it runs (docs/console.md)"
exec .venv/bin/fieldguard run --print-every 2 "$@"
