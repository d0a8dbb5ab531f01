#!/usr/bin/env bash
# pyinstall.sh PIP-INSTALL-ARGS...: install into the project's .venv (or $PY) with uv, or with
# pip where uv cannot be had. Quiet, as the set-up scripts are. Paths are the caller's (each
# set-up script runs from the project's root).
#
# Why uv: the environment is built from nothing in every CI run and every fresh clone, and pip
# spent most of a minute of CPU on it (tools/setup.sh 50 s, the test extra 29 s on this 2-core
# host, 2026-12-06), mostly unpacking and resolving one package at a time; uv (Astral's
# installer, PyPI's `uv` package, installed into the venv by pip) does the same installs in
# 4 s and 25 s (that is the builds of PyGObject, pycairo and systemd-python from source, which
# neither tool avoids) and resolved the same 76 versions as pip here. It reads no pip
# configuration, so a machine whose pip needs an index of its own must give uv it too
# (UV_INDEX_URL); without uv (no registry, a failed install) this falls back to pip.
set -euo pipefail
PY=${PY:-.venv/bin/python}
# copies, not hardlinks: the cache and the venv are often on different filesystems
export UV_LINK_MODE=${UV_LINK_MODE:-copy}
if ! "$PY" -m uv --version >/dev/null 2>&1; then
  "$PY" -m pip install --quiet uv >/dev/null 2>&1 || true
fi
if "$PY" -m uv --version >/dev/null 2>&1; then
  exec "$PY" -m uv pip install --python "$PY" --quiet "$@"
fi
echo "pyinstall: uv is not available; installing with pip" >&2
exec "$PY" -m pip install --quiet "$@"
