#!/usr/bin/env bash
# Sets up and runs the whole test suite. `.ci/run` calls exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/hw_system_deps.sh   # Debian: aravis + fake GigE camera, socat, iproute2, build deps
bash tools/setup.sh
# The whole suite (no arguments): the simulator's renderer compiled once now (numba caches it
# beside its source: ~40 s of CPU, cold), while the test tools install, rather than by each
# of the first phase's workers at once. A failure here costs only time: said, and carried on.
warm_pid=""
if [ "$#" -eq 0 ]; then
  warm=$(mktemp -d)
  .venv/bin/python -m appliance.cli sim stubble-day --frames 1 --stereo-scale 0.25 \
    --sensors stereo,laser,rgbd --out "$warm/run" >"$warm/log" 2>&1 &
  warm_pid=$!
fi
# the test tools (PyGObject builds against the GObject headers hw_system_deps.sh installed)
stamp=.venv/.fieldguard-test-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "test: installing the test tools into .venv" >&2
  bash tools/pyinstall.sh -e '.[test]'
  touch "$stamp"
fi
# again, now that .venv exists: its Python half (the freenect binding, built against the
# libfreenect headers installed above) is skipped while there is no .venv
bash tools/hw_system_deps.sh
bash tools/ci_system_deps.sh   # headless MAVProxy
if [ "$#" -gt 0 ]; then
  exec .venv/bin/python -m pytest "$@"
fi
# The whole suite, in two phases (tests/conftest.py says which module is which): the modules
# that run in simulated time on pytest-xdist's workers, one per core and one more (the soak's
# test spends its ~95 s waiting for the soak, whose processes use half a core at nice -10; up
# to 5), the soak among them; then every module with a wall-clock deadline, alone, one test
# at a time. On this 2-core host: 649 s in one process, 268 + 288 s with 2 workers, 221 s for
# the first phase with 3 (2026-12-06).
if ! wait "$warm_pid"; then
  echo "test: compiling the renderer beforehand failed (the workers will): $(tail -3 "$warm/log")" >&2
fi
rm -rf "$warm"
workers=$(( $(nproc 2>/dev/null || echo 1) + 1 ))
[ "$workers" -gt 5 ] && workers=5
echo "test: environment ready after ${SECONDS} s" >&2
echo "test: 1 of 2: the simulated-time modules and the soak, on $workers workers" >&2
rc=0
.venv/bin/python -m pytest --phase simulated -n "$workers" --dist loadfile \
  --no-loadscope-reorder || rc=$?
echo "test: 2 of 2 (at ${SECONDS} s): the modules with wall-clock deadlines, alone" >&2
.venv/bin/python -m pytest --phase wall-clock || rc=$?
echo "test: done after ${SECONDS} s" >&2
if [ "$rc" -ne 0 ]; then
  echo "test: FAILED (exit $rc): see the failures above" >&2
fi
exit "$rc"
