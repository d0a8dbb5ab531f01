#!/usr/bin/env bash
# Sets up and runs the whole test suite. `.ci/run` calls exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."
# Byte-code caches written, whatever the host says: with PYTHONDONTWRITEBYTECODE set (it is on
# these hosts and in their CI) nothing the suite imports is ever cached, so each of its
# Python processes (well over a hundred: CLI runs, daemons, campaigns, Ray's workers, the
# soak's box) compiled the project and every package uv installed (uv compiles no byte-code
# at install) from source again, ~1.4 CPU-s for a campaign's; with the campaign's Poisson
# interval off scipy.stats beside it the suite's CPU fell by a quarter (2026-12-07,
# docs/reliability.md). Written once, beside each source (the checkout's are git-ignored),
# on first import.
unset PYTHONDONTWRITEBYTECODE
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
# The whole suite, in two parts at once (tests/conftest.py says which module is which):
#  - the modules that run in simulated time (lock-step daemons, pace 0: nothing they check
#    depends on how fast they run), the soak's test among them, on pytest-xdist's workers (one
#    per core and one more: the soak's test spends its ~95 s waiting for the soak; up to 5), at
#    the lowest CPU priority the kernel has (SCHED_IDLE: they get a core only when nothing else
#    wants it, and a waking process of normal priority takes it from them at once);
#  - beside them, every module with a wall-clock deadline, one test at a time, at normal
#    priority: it used ~75 % of one core alone, the rest of the machine idle (2026-12-06: 240 s
#    for the first part alone, then 281 s for this one).
# The soak puts itself back to normal priority (tools/soak.py; it runs at nice -10 in a session
# of its own). The simulated part's output is printed when both have ended (tools/test_parts.sh).
t_wait=$SECONDS
if ! wait "$warm_pid"; then
  echo "test: compiling the renderer beforehand failed (the workers will): $(tail -3 "$warm/log")" >&2
fi
# where the set-up's time goes (the renderer's compile, or the installs beside it)
echo "test: the installs were done after ${t_wait} s; the renderer's compile $(( SECONDS - t_wait )) s later" >&2
rm -rf "$warm"
workers=$(( $(nproc 2>/dev/null || echo 1) + 1 ))
[ "$workers" -gt 5 ] && workers=5
echo "test: environment ready after ${SECONDS} s" >&2
echo "test: the simulated-time modules and the soak on $workers workers, beside the modules with wall-clock deadlines" >&2
rc=0
bash tools/test_parts.sh \
  "--phase simulated -n $workers --dist loadfile --no-loadscope-reorder -o cache_dir=.pytest_cache/simulated" \
  "--phase wall-clock" || rc=$?
echo "test: done after ${SECONDS} s" >&2
if [ "$rc" -ne 0 ]; then
  echo "test: FAILED (exit $rc): see the failures above" >&2
fi
exit "$rc"
