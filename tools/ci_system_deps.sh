#!/usr/bin/env bash
# System packages the vehicle-link tests need (idempotent; Debian 12; run as root in CI).
#   iproute2: `ip netns` for the CAN test's private multicast loopback.
#   chromium, chromium-driver: the web console's browser test (headless, driven by selenium).
# Python packages come from pyproject (pymavlink, python-can[multicast], cantools; test extra:
# can-j1939, MAVProxy installed with --no-deps, see docs/vehicle-links.md).
# Sourced (tools/hw_system_deps.sh does), it only defines apt_ensure and pip_ensure.
set -euo pipefail

# apt_ensure PKG...: install those of the Debian packages that are not installed yet (root is
# needed only when something is missing)
apt_ensure() {
  local missing=() p
  for p in "$@"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  if [ "$(id -u)" -ne 0 ]; then
    echo "$(basename "$0"): need root to install: ${missing[*]}" >&2
    return 1
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
}

# pip_ensure MODULE PIP-ARGS...: pip install PIP-ARGS into $PY unless MODULE imports
pip_ensure() {
  local mod=$1
  shift
  "$PY" -c "import $mod" 2>/dev/null || PY=$PY bash "$(dirname "${BASH_SOURCE[0]}")/pyinstall.sh" "$@"
}

PY=${PY:-.venv/bin/python}
[[ "${BASH_SOURCE[0]}" != "$0" ]] && return 0

apt_ensure iproute2 chromium chromium-driver
# MAVProxy without its GUI dependencies (vtk, matplotlib, opencv: over 1 GB)
if [ -x "$PY" ] && ! "$PY" -c "import MAVProxy" 2>/dev/null; then
  PY=$PY bash tools/pyinstall.sh pymavlink defusedxml pyserial pynmeagps
  PY=$PY bash tools/pyinstall.sh --no-deps MAVProxy
fi
