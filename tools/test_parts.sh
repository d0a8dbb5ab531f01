#!/usr/bin/env bash
# Runs two pytest invocations at once and exits non-zero if either failed (tools/test.sh's
# whole suite; tests/test_test_parts.py runs it on tiny suites that pass and fail).
#   bash tools/test_parts.sh "LOW-PRIORITY PYTEST ARGS" "NORMAL-PRIORITY PYTEST ARGS"
# The first runs at the lowest CPU priority the kernel has (SCHED_IDLE via chrt; nice 19
# without it), its output kept aside and printed when both have ended; the second runs in
# the foreground at normal priority. Arguments are split on whitespace (no quoting).
# Exit status: the foreground's if it failed, else the background's.
set -uo pipefail        # no -e: every status here is read on purpose
if [ "$#" -ne 2 ]; then
  echo "usage: test_parts.sh 'LOW-PRIORITY PYTEST ARGS' 'NORMAL-PRIORITY PYTEST ARGS'" >&2
  exit 2
fi
read -r -a low_args <<<"$1"
read -r -a fg_args <<<"$2"
py=${FIELDGUARD_PYTHON:-.venv/bin/python}
if chrt --idle 0 true 2>/dev/null; then
  low=(chrt --idle 0)
else
  low=(nice -n 19)            # no chrt: the lowest nice instead
fi
echo "test: the low-priority part under ${low[*]}, beside the normal-priority part" >&2
bg_log=$(mktemp)
"${low[@]}" "$py" -m pytest "${low_args[@]}" >"$bg_log" 2>&1 &
bg_pid=$!
# On an early exit (a signal) stop the background part; on the normal path it has been
# waited for and nothing is left to kill. `|| true`: a trap's failing command must never
# become the script's exit status (the defect of 2026-12-06: every run exited 1).
trap 'kill "$bg_pid" 2>/dev/null || true; rm -f "$bg_log"' EXIT
rc=0
"$py" -m pytest "${fg_args[@]}" || rc=$?
echo "test: the normal-priority part ended at ${SECONDS} s (exit $rc); the low-priority part:" >&2
bg_rc=0
wait "$bg_pid" || bg_rc=$?
cat "$bg_log"
echo "test: the low-priority part exit $bg_rc" >&2
if [ "$rc" -eq 0 ] && [ "$bg_rc" -ne 0 ]; then rc=$bg_rc; fi
exit "$rc"
