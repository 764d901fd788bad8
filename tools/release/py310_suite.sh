#!/usr/bin/env bash
# The whole test suite on Python 3.10, in an Ubuntu 22.04 (jammy) root: the Python that ROS 2
# Humble and JetPack 6 ship. Not in CI (it builds a root first). Run as root:
#
#   bash tools/release/py310_suite.sh [WORKDIR] [PYTEST ARGS...]   (default WORKDIR: /var/tmp/spiel-jammy)
#
# 1. debootstrap jammy (minbase, main + universe: python3-venv) for the host's architecture
#    from archive.ubuntu.com (SPIEL_UBUNTU_MIRROR), kept in WORKDIR/root between runs.
# 2. The checkout (working tree, without .git and .venv) is copied to /src there and installed
#    into /opt/venv with '[test]', every dependency a binary wheel (--only-binary).
# 3. `python -m pytest` runs in /src with the extra arguments (default: the whole suite).
# Debian packages no Python 3.10 and PyPI no interpreter; Ubuntu's archive has jammy's 3.10.
set -euo pipefail

REPO=$(cd "$(dirname "$0")/../.." && pwd)
WORK=${1:-/var/tmp/spiel-jammy}
shift || true
MIRROR=${SPIEL_UBUNTU_MIRROR:-http://archive.ubuntu.com/ubuntu}
ROOT=$WORK/root
HOST_CA=${SPIEL_HOST_CA:-/etc/ssl/certs/ca-certificates.crt}  # a TLS proxy's CA lives there
T0=$(date +%s)

step() { echo "== [$(($(date +%s) - T0)) s] $*"; }
die() { echo "py310_suite: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || die "run as root (debootstrap, chroot)"
command -v debootstrap >/dev/null || { step "installing debootstrap"; apt-get install -y -qq debootstrap >/dev/null; }
mkdir -p "$WORK"

cleanup() {
    for m in "$ROOT/proc" "$ROOT/dev/pts" "$ROOT/dev"; do mountpoint -q "$m" && umount -l "$m"; done
    return 0
}
trap cleanup EXIT

in_root() { chroot "$ROOT" /usr/bin/env -i HOME=/root PATH=/opt/venv/bin:/usr/bin:/bin \
    PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_DEFAULT_TIMEOUT=180 PIP_CERT=/etc/ssl/host-ca.crt "$@"; }

if [ ! -e "$ROOT/.spiel-root-done" ]; then
    step "debootstrap jammy into $ROOT"
    rm -rf "$ROOT"
    debootstrap --variant=minbase --components=main,universe \
        --include=python3,python3-venv,ca-certificates jammy "$ROOT" "$MIRROR" >"$WORK/debootstrap.log"
    touch "$ROOT/.spiel-root-done"
fi
# the tests open pseudo-terminals (the serial link) and resolve localhost (UDP output)
mountpoint -q "$ROOT/proc" || mount -t proc proc "$ROOT/proc"
mountpoint -q "$ROOT/dev" || mount --bind /dev "$ROOT/dev"
mountpoint -q "$ROOT/dev/pts" || mount --bind /dev/pts "$ROOT/dev/pts"
cp /etc/resolv.conf "$ROOT/etc/resolv.conf"
[ -s "$ROOT/etc/hosts" ] || printf '127.0.0.1 localhost\n::1 localhost ip6-localhost\n' >"$ROOT/etc/hosts"
cp "$HOST_CA" "$ROOT/etc/ssl/host-ca.crt"

step "copying the checkout and installing it with [test]"
rm -rf "$ROOT/src" && mkdir -p "$ROOT/src"
tar -C "$REPO" --exclude=.git --exclude=.venv --exclude='__pycache__' --exclude='*.egg-info' \
    --exclude=build -cf - . | tar -C "$ROOT/src" -xf -
[ -e "$ROOT/opt/venv/bin/pip" ] || { rm -rf "$ROOT/opt/venv" && in_root python3 -m venv /opt/venv; }
in_root sh -c 'cd /src && pip install -q --only-binary=:all: --no-binary=spiel-edge ".[test]"'
in_root python -c 'import platform, sys; print("root:", platform.machine(), sys.version.split()[0])'
in_root pip list --format=freeze | grep -i -E '^(numpy|numba|onnxruntime|tomli|mcap|rosbags)=' || true

step "python -m pytest ${*:-(the whole suite)} on Python 3.10"
in_root sh -c "cd /src && python -m pytest -q -p no:cacheprovider $*"
step "the suite passed on Python 3.10"
