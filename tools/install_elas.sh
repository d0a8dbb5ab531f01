#!/bin/sh
# Optional: LIBELAS (Geiger et al., the matcher of the stereo paper) through the pyelas
# binding, for `matcher = "elas"`. GPLv3 — never a dependency of fieldguard, and not installed
# by setup.sh or the tests (they skip the ELAS checks without it). pyelas 1.0.1 as published
# on the package index does not build (its build does not find numpy's headers); this script
# builds it into the project's .venv with them on the include path.
#
#     ./tools/install_elas.sh        (after ./tools/setup.sh)
set -eu
cd "$(dirname "$0")/.."
PY=.venv/bin/python
[ -x "$PY" ] || { echo "install_elas: no .venv here: run ./tools/setup.sh first" >&2; exit 2; }
"$PY" -m pip install --quiet wheel cython setuptools
NP=$("$PY" -c "import numpy; print(numpy.get_include())")
CFLAGS="-I$NP" "$PY" -m pip install --quiet --no-build-isolation "pyelas==1.0.1"
"$PY" -c "import elas; print('pyelas installed: matcher = \"elas\" is available (GPLv3)')"
