#!/usr/bin/env bash
# Creates .venv (once) and installs fieldguard into it: what the product needs, nothing more
# (the test tools are tools/test.sh's; PyGObject, one of them, builds from source and needs the
# GObject headers). Idempotent.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)" >&2
  "$PY" -m venv .venv
fi
stamp=.venv/.fieldguard-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "setup: installing fieldguard and its dependencies (first time: a minute or two)" >&2
  bash tools/pyinstall.sh -e .   # uv, or pip where uv cannot be had
  touch "$stamp"
fi
