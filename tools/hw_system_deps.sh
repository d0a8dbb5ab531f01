#!/usr/bin/env bash
# System and Python packages the hardware-driver tests need (idempotent; Debian 12; root for apt).
#   aravis-tools (arv-fake-gv-camera-0.8), aravis-tools-cli (arv-tool-0.8), gir1.2-aravis-0.8:
#     the GigE Vision library, its fake camera and its introspection data
#   libgirepository1.0-dev libcairo2-dev pkg-config gcc python3-dev: to build PyGObject<3.51
#     (newer PyGObject needs girepository-2.0, which Debian 12 lacks)
#   socat: the pty pair between the strobe driver and its emulator
#   iproute2: `ip netns` for the fake cameras' private network
#   libsystemd-dev: to build systemd-python (the `systemd` extra, in the test extra too), which
#     the daemon uses for sd_notify and the journal (appliance/service.py; pkg-config finds it)
#   libfreenect-dev libfreenect-bin: the Kinect library (headers: the `freenect` Python binding
#     builds against them, and so does the fakenect preload stub) and fakenect, its playback
#     library, which the freenect driver's tests play recorded dumps through
set -euo pipefail
cd "$(dirname "$0")/.."
source tools/ci_system_deps.sh          # apt_ensure, pip_ensure
apt_ensure aravis-tools aravis-tools-cli gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev \
  pkg-config gcc python3-dev socat iproute2 libfreenect-dev libfreenect-bin libsystemd-dev
if [ -x "$PY" ]; then
  pip_ensure gi 'PyGObject<3.51'
  pip_ensure serial pyserial
  pip_ensure sick_scan_tcp sick-scan-tcp
  pip_ensure freenect freenect
fi
