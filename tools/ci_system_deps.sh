#!/usr/bin/env bash
# System packages the vehicle-link tests need (idempotent; Debian 12; run as root in CI).
#   iproute2: `ip netns` for the CAN test's private multicast loopback.
# Python packages come from pyproject (pymavlink, python-can[multicast], cantools; test extra:
# can-j1939, MAVProxy installed with --no-deps, see docs/vehicle-links.md).
set -euo pipefail
missing=()
command -v ip >/dev/null 2>&1 || missing+=(iproute2)
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" -ne 0 ]; then
    echo "ci_system_deps: need root to install: ${missing[*]}" >&2
    exit 1
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
# MAVProxy without its GUI dependencies (vtk, matplotlib, opencv: over 1 GB)
PY=${PY:-.venv/bin/python}
if [ -x "$PY" ] && ! "$PY" -c "import MAVProxy" 2>/dev/null; then
  "$PY" -m pip install --quiet pymavlink defusedxml pyserial pynmeagps
  "$PY" -m pip install --quiet --no-deps MAVProxy
fi
