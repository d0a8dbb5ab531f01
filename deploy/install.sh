#!/usr/bin/env bash
# Install (or upgrade) fieldguard as a systemd service.
#
#   sudo deploy/install.sh [--root DIR] [--pip-args "ARGS"] [--no-enable]
#
# - a virtual environment in /opt/fieldguard/venv with fieldguard from this source tree, and
#   /usr/local/bin/fieldguard linked to its command;
# - /etc/fieldguard/fieldguard.toml from deploy/fieldguard.toml, NEVER overwritten: on upgrade a
#   changed default goes to fieldguard.toml.new beside it;
# - the udev rules, the unit, the system user `fieldguard`; the unit enabled (not started).
# --root DIR installs into DIR as if it were / (for tests and image builds).
set -euo pipefail
SRC=$(cd "$(dirname "$0")/.." && pwd)
ROOT=""
PIP_ARGS=""
ENABLE=1
PY=${PYTHON:-python3}
while [ $# -gt 0 ]; do
  case "$1" in
    --root) ROOT=$(realpath -m "$2"); shift 2 ;;
    --pip-args) PIP_ARGS=$2; shift 2 ;;
    --no-enable) ENABLE=0; shift ;;
    -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
    *) echo "install.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
if [ -z "$ROOT" ] && [ "$(id -u)" -ne 0 ]; then
  echo "install.sh: run as root (or give --root DIR)" >&2; exit 1
fi
say() { echo "install: $*"; }
OPT="$ROOT/opt/fieldguard"; ETC="$ROOT/etc/fieldguard"
UNIT_DIR="$ROOT/etc/systemd/system"; UDEV_DIR="$ROOT/etc/udev/rules.d"

# 1. user
if [ -z "$ROOT" ]; then
  if ! id fieldguard >/dev/null 2>&1; then
    say "creating system user fieldguard"
    useradd --system --home-dir /var/lib/fieldguard --no-create-home --shell /usr/sbin/nologin \
      --groups dialout,plugdev,video fieldguard 2>/dev/null \
      || useradd --system --home-dir /var/lib/fieldguard --no-create-home --shell /usr/sbin/nologin fieldguard
  fi
else
  say "--root: not creating the user (the unit runs as User=fieldguard; create it in the image)"
fi

# 2. virtual environment
mkdir -p "$OPT"
if [ ! -x "$OPT/venv/bin/python" ]; then
  say "creating $OPT/venv"
  "$PY" -m venv "$OPT/venv"
fi
say "installing fieldguard from $SRC"
# built from a private copy of what the package is made of, never in the source tree: pip
# builds a tree in place (build/ and fieldguard.egg-info/ beside the sources), so every
# install left them in the checkout, and two installs from one tree at once (the suite's two
# install tests, 2026-12-08) tore down each other's build directory mid-build
STAGE=$(mktemp -d)
trap 'rm -rf "$STAGE"' EXIT
tar -C "$SRC" --exclude=__pycache__ -cf - pyproject.toml README.md appliance hal drivers \
  | tar -C "$STAGE" -xf -
# shellcheck disable=SC2086
"$OPT/venv/bin/python" -m pip install --quiet $PIP_ARGS "$STAGE"
# the command on PATH: /usr/local/bin/fieldguard -> the venv's (a path inside the target
# system, also with --root)
mkdir -p "$ROOT/usr/local/bin"
if [ -e "$ROOT/usr/local/bin/fieldguard" ] && [ ! -L "$ROOT/usr/local/bin/fieldguard" ]; then
  say "kept $ROOT/usr/local/bin/fieldguard (not ours); the command is $OPT/venv/bin/fieldguard"
else
  ln -sfn /opt/fieldguard/venv/bin/fieldguard "$ROOT/usr/local/bin/fieldguard"
  say "linked /usr/local/bin/fieldguard"
fi
cp "$SRC/README.md" "$OPT/README.md"
mkdir -p "$OPT/docs" && cp -r "$SRC/docs/." "$OPT/docs/"

# 3. configuration: never overwritten
mkdir -p "$ETC"
if [ ! -f "$ETC/fieldguard.toml" ]; then
  install -m 0640 "$SRC/deploy/fieldguard.toml" "$ETC/fieldguard.toml"
  say "wrote $ETC/fieldguard.toml"
elif ! cmp -s "$SRC/deploy/fieldguard.toml" "$ETC/fieldguard.toml"; then
  install -m 0640 "$SRC/deploy/fieldguard.toml" "$ETC/fieldguard.toml.new"
  say "kept your $ETC/fieldguard.toml; the new default is beside it as fieldguard.toml.new"
fi

# 4. udev rules and the unit
mkdir -p "$UDEV_DIR" "$UNIT_DIR"
install -m 0644 "$SRC/deploy/99-fieldguard.rules" "$UDEV_DIR/99-fieldguard.rules"
install -m 0644 "$SRC/deploy/fieldguard.service" "$UNIT_DIR/fieldguard.service"
if [ -z "$ROOT" ] && command -v udevadm >/dev/null 2>&1; then
  udevadm control --reload-rules 2>/dev/null || true
fi
if [ "$ENABLE" = 1 ]; then
  if [ -n "$ROOT" ]; then
    systemctl --root="$ROOT" enable fieldguard.service
  else
    systemctl daemon-reload 2>/dev/null || true
    systemctl enable fieldguard.service
  fi
fi
say "done. Check the config:  fieldguard config check /etc/fieldguard/fieldguard.toml"
say "start it:               systemctl start fieldguard; then: fieldguard status"
