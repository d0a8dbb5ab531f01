#!/usr/bin/env bash
# Sets up and runs the whole test suite. `.ci/run` calls exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/hw_system_deps.sh   # Debian: aravis + fake GigE camera, socat, iproute2, build deps
bash tools/setup.sh
# the test tools (PyGObject builds against the GObject headers hw_system_deps.sh installed)
stamp=.venv/.fieldguard-test-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "test: installing the test tools into .venv" >&2
  .venv/bin/python -m pip install --quiet -e '.[test]'
  touch "$stamp"
fi
# again, now that .venv exists: its Python half (the freenect binding, built against the
# libfreenect headers installed above) is skipped while there is no .venv
bash tools/hw_system_deps.sh
bash tools/ci_system_deps.sh   # headless MAVProxy
exec .venv/bin/python -m pytest "$@"
