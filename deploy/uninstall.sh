#!/usr/bin/env bash
# Remove fieldguard: the unit, the udev rules and the virtual environment. The configuration
# (/etc/fieldguard) and the state (/var/lib/fieldguard: incidents, recordings) are KEPT unless
# --purge is given: no data lost by accident.
#
#   sudo deploy/uninstall.sh [--root DIR] [--purge]
set -euo pipefail
ROOT=""; PURGE=0
while [ $# -gt 0 ]; do
  case "$1" in
    --root) ROOT=$(realpath -m "$2"); shift 2 ;;
    --purge) PURGE=1; shift ;;
    -h|--help) sed -n '2,7p' "$0"; exit 0 ;;
    *) echo "uninstall.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
if [ -z "$ROOT" ] && [ "$(id -u)" -ne 0 ]; then
  echo "uninstall.sh: run as root (or give --root DIR)" >&2; exit 1
fi
say() { echo "uninstall: $*"; }
if [ -f "$ROOT/etc/systemd/system/fieldguard.service" ]; then
  if [ -n "$ROOT" ]; then
    systemctl --root="$ROOT" disable fieldguard.service || true
  else
    systemctl stop fieldguard.service 2>/dev/null || true
    systemctl disable fieldguard.service 2>/dev/null || true
  fi
fi
rm -f "$ROOT/etc/systemd/system/fieldguard.service" "$ROOT/etc/udev/rules.d/99-fieldguard.rules"
if [ "$(readlink "$ROOT/usr/local/bin/fieldguard" 2>/dev/null)" = /opt/fieldguard/venv/bin/fieldguard ]; then
  rm -f "$ROOT/usr/local/bin/fieldguard"
fi
rm -rf "$ROOT/opt/fieldguard"
[ -z "$ROOT" ] && systemctl daemon-reload 2>/dev/null || true
if [ "$PURGE" = 1 ]; then
  rm -rf "$ROOT/etc/fieldguard" "$ROOT/var/lib/fieldguard"
  [ -z "$ROOT" ] && userdel fieldguard 2>/dev/null || true
  say "removed everything, configuration and state included"
else
  say "removed; kept $ROOT/etc/fieldguard and $ROOT/var/lib/fieldguard (use --purge to remove)"
fi
