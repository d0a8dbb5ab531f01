#!/usr/bin/env bash
# System and Python packages the hardware-driver tests need (idempotent; Debian 12; root for apt).
#   aravis-tools (arv-fake-gv-camera-0.8), aravis-tools-cli (arv-tool-0.8), gir1.2-aravis-0.8:
#     the GigE Vision library, its fake camera and its introspection data
#   libgirepository1.0-dev libcairo2-dev pkg-config gcc python3-dev: to build PyGObject<3.51
#     (newer PyGObject needs girepository-2.0, which Debian 12 lacks)
#   socat: the pty pair between the strobe driver and its emulator
#   iproute2: `ip netns` for the fake cameras' private network
#   libfreenect-dev libfreenect-bin: the Kinect library (headers: the `freenect` Python binding
#     builds against them, and so does the fakenect preload stub) and fakenect, its playback
#     library, which the freenect driver's tests play recorded dumps through
set -euo pipefail
cd "$(dirname "$0")/.."
pkgs=(aravis-tools aravis-tools-cli gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev
      pkg-config gcc python3-dev socat iproute2 libfreenect-dev libfreenect-bin)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" -ne 0 ]; then
    echo "hw_system_deps: need root to install: ${missing[*]}" >&2
    exit 1
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
PY=${PY:-.venv/bin/python}
if [ -x "$PY" ]; then
  "$PY" -c "import gi" 2>/dev/null || "$PY" -m pip install --quiet 'PyGObject<3.51'
  "$PY" -c "import serial" 2>/dev/null || "$PY" -m pip install --quiet pyserial
  "$PY" -c "import sick_scan_tcp" 2>/dev/null || "$PY" -m pip install --quiet sick-scan-tcp
  "$PY" -c "import freenect" 2>/dev/null || "$PY" -m pip install --quiet freenect
fi
