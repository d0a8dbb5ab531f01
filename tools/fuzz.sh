#!/usr/bin/env bash
# tools/fuzz.sh TARGET MINUTES: one fuzz target (tests/fuzz/) for MINUTES under atheris
# (coverage-guided, libFuzzer), niced, starting from the committed corpus. Inputs that add
# coverage are merged back into tests/fuzz/corpus/TARGET/ (commit them); a crash, hang
# (-timeout) or memory blow-up (-rss_limit_mb) leaves its input in tests/fuzz/crashes/ and
# fails. Each run appends one line to tests/fuzz/fuzz-log.tsv (the figures in
# docs/reliability.md): date, target, seconds, executions, result, commit;
# `tools/fuzz.sh --summary` adds them up per target.
#   TARGETS: cola strobe mavlink j1939 runfolder config annotations cue-model status console
#   env: FUZZ_NICE (15), FUZZ_TIMEOUT_S (20, one input), FUZZ_RSS_MB (2048), PY (.venv/bin/python)
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = "--summary" ]; then
  # fuzzing time per target so far (tests/fuzz/fuzz-log.tsv): the table in docs/reliability.md
  printf '| target | runs | minutes | inputs | runs stopped by a failing input |\n|---|---|---|---|---|\n'
  for t in cola strobe mavlink j1939 runfolder config annotations cue-model status console; do
    awk -F'\t' -v t="$t" '$2 == t { n++; s += $3; i += $4; if ($5 ~ /^defect/) d++ }
      END { printf "| `%s` | %d | %.1f | %d | %d |\n", t, n, s / 60, i, d }' tests/fuzz/fuzz-log.tsv
  done
  exit 0
fi
if [ $# -ne 2 ]; then
  echo "usage: tools/fuzz.sh TARGET MINUTES | tools/fuzz.sh --summary" >&2
  exit 2
fi
target=$1 minutes=$2
PY=${PY:-.venv/bin/python}
if ! "$PY" -c "import tests.fuzz.common as c, sys; sys.exit(0 if '$target' in c.TARGETS else 1)"; then
  echo "fuzz.sh: error: unknown target '$target' (see tests/fuzz/common.py TARGETS)" >&2
  exit 2
fi
if ! "$PY" -c "import atheris" 2>/dev/null; then
  echo "fuzz.sh: error: atheris is not installed in $PY (pip install atheris; the test extra has it)" >&2
  exit 2
fi
secs=$(awk "BEGIN { printf \"%d\", $minutes * 60 }")
corpus=tests/fuzz/corpus/$target
crashes=tests/fuzz/crashes
work=${TMPDIR:-/tmp}/fieldguard-fuzz-work/$target
mkdir -p "$corpus" "$crashes" "$work"
log=$work/fuzz.log
# libFuzzer's merge re-runs argv[0]: an executable that is this target
wrapper=$work/fuzz-$target
printf '#!/bin/sh\nexec "%s" -m tests.fuzz.run "%s" "$@"\n' "$(cd "$(dirname "$PY")" && pwd)/$(basename "$PY")" "$target" >"$wrapper"
chmod +x "$wrapper"
export FUZZ_ARGV0=$wrapper PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
commit=$(git rev-parse --short HEAD 2>/dev/null || echo unknown)
start=$(date +%s)
set +e
nice -n "${FUZZ_NICE:-15}" "$PY" -m tests.fuzz.run "$target" \
  -max_total_time="$secs" -timeout="${FUZZ_TIMEOUT_S:-20}" -rss_limit_mb="${FUZZ_RSS_MB:-2048}" \
  -max_len=65536 -print_final_stats=1 -artifact_prefix="$crashes/$target-" \
  "$work" "$corpus" >"$log" 2>&1
rc=$?
set -e
elapsed=$(( $(date +%s) - start ))
runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -1)
cov=$(grep -oE '#[0-9]+.*cov: [0-9]+' "$log" | tail -1 | grep -oE 'cov: [0-9]+' | grep -oE '[0-9]+')
if [ $rc -eq 0 ]; then
  result=clean
else
  art=$(grep -oE "(Test unit written to|artifact_prefix.*) [^ ]+" "$log" | tail -1 | awk '{print $NF}')
  result="defect:${art:-see $log}"
fi
# keep only the inputs that add coverage to the committed corpus
nice -n "${FUZZ_NICE:-15}" "$PY" -m tests.fuzz.run "$target" -merge=1 -timeout="${FUZZ_TIMEOUT_S:-20}" \
  -artifact_prefix="$work/merge-" "$corpus" "$work" >"$work/merge.log" 2>&1 || true
printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$(date -u +%FT%TZ)" "$target" "$elapsed" "${runs:-?}" \
  "$result" "$commit" >>tests/fuzz/fuzz-log.tsv
echo "fuzz $target: ${elapsed} s, ${runs:-?} inputs, coverage ${cov:-?}, corpus $(ls "$corpus" | wc -l) files, $result"
echo "  log: $log"
[ $rc -eq 0 ]
