#!/usr/bin/env bash
# aarch64 smoke test under emulation (not in CI: it takes many minutes). Run as root:
#
#   bash tools/release/aarch64_smoke.sh [WORKDIR]        (default WORKDIR: /var/tmp/spiel-aarch64)
#
# 1. qemu-user from Debian trixie (qemu 10): bookworm's qemu 7.2 crashes importing
#    onnxruntime >= 1.28. The .deb comes from a private apt state under WORKDIR/apt, so the
#    host's apt sources are left alone; its binaries are static, registered with binfmt_misc
#    under our own name with the F flag (the kernel keeps the interpreter open: works in a
#    chroot without copying qemu into it). The entry is removed on exit.
# 2. A Debian arm64 root (debootstrap, bookworm: Python 3.11) at WORKDIR/root, kept between
#    runs (delete it to start afresh).
# 3. The checkout (working tree, without .git and .venv) is installed there with '[test]',
#    the core and framing tests run, and `spiel-edge run --port sim://` is compared with the
#    host's output: every position within 0.01 mm.
# SPIEL_SMOKE_ROOT_ONLY=1 stops after step 2; SPIEL_ARM_SUITE picks the Debian suite.
# SPIEL_SMOKE_EXEC="command" runs that host command after step 2 instead of steps 3-4, with
# the root's /proc, /dev, /sys mounted, qemu registered and ARM_ROOT set to the root (the
# release script builds the aarch64 wheel this way: tools/release/build_wheels.py).
# Timings under emulation mean nothing; the run time of each step is printed.
set -euo pipefail

REPO=$(cd "$(dirname "$0")/../.." && pwd)
WORK=${1:-/var/tmp/spiel-aarch64}
SUITE=${SPIEL_ARM_SUITE:-bookworm}
MIRROR=${SPIEL_DEBIAN_MIRROR:-http://deb.debian.org/debian}
FRAMES=${SPIEL_SMOKE_FRAMES:-30}
BINFMT=/proc/sys/fs/binfmt_misc
ENTRY=${SPIEL_QEMU_ENTRY:-spiel-qemu-aarch64}
ROOT=$WORK/root
T0=$(date +%s)

step() { echo "== [$(($(date +%s) - T0)) s] $*"; }
die() { echo "aarch64_smoke: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || die "run as root (binfmt_misc, debootstrap, chroot)"
command -v debootstrap >/dev/null || { step "installing debootstrap"; apt-get install -y -qq debootstrap >/dev/null; }
mkdir -p "$WORK"

fetch_qemu() {
    local apt=$WORK/apt
    [ -x "$WORK/qemu/usr/bin/qemu-aarch64" ] && return
    step "fetching qemu-user from Debian trixie (private apt state in $apt)"
    mkdir -p "$apt/lists/partial" "$apt/cache/archives/partial" "$WORK/qemu"
    echo "deb [signed-by=/usr/share/keyrings/debian-archive-trixie-stable.gpg] $MIRROR trixie main" \
        >"$apt/sources.list"
    local opts=(-o "Dir::Etc::SourceList=$apt/sources.list" -o "Dir::Etc::SourceParts=/nonexistent"
        -o "Dir::State::Lists=$apt/lists" -o "Dir::Cache=$apt/cache" -o "Debug::NoLocking=1"
        -o "APT::Sandbox::User=root")
    apt-get "${opts[@]}" -qq update
    (cd "$apt" && rm -f qemu-user_*.deb && apt-get "${opts[@]}" -qq download qemu-user)
    dpkg-deb -x "$apt"/qemu-user_*.deb "$WORK/qemu"
}

register_binfmt() {
    mountpoint -q "$BINFMT" || mount -t binfmt_misc binfmt_misc "$BINFMT"
    [ -e "$BINFMT/$ENTRY" ] && echo -1 >"$BINFMT/$ENTRY"
    local magic='\x7fELF\x02\x01\x01\x00\x00\x00\x00\x00\x00\x00\x00\x00\x02\x00\xb7\x00'
    local mask='\xff\xff\xff\xff\xff\xff\xff\x00\xff\xff\xff\xff\xff\xff\xff\xff\xfe\xff\xff\xff'
    # newest entries match first, so ours wins over an older qemu-aarch64 from bookworm
    echo ":$ENTRY:M::$magic:$mask:$WORK/qemu/usr/bin/qemu-aarch64:FOC" >"$BINFMT/register"
}

cleanup() {
    for m in "$ROOT/proc" "$ROOT/dev" "$ROOT/sys"; do mountpoint -q "$m" && umount -l "$m"; done
    [ -e "$BINFMT/$ENTRY" ] && echo -1 >"$BINFMT/$ENTRY"
    return 0
}
trap cleanup EXIT

make_root() {
    [ -x "$ROOT/usr/bin/python3" ] && [ -e "$ROOT/.spiel-root-done" ] && return
    step "debootstrap $SUITE arm64 into $ROOT"
    rm -rf "$ROOT"
    debootstrap --arch=arm64 --variant=minbase --foreign \
        --include=python3,python3-venv,ca-certificates "$SUITE" "$ROOT" "$MIRROR" >"$WORK/debootstrap.log"
    chroot "$ROOT" /debootstrap/debootstrap --second-stage >>"$WORK/debootstrap.log"
    touch "$ROOT/.spiel-root-done"
}

# the host's CA bundle: a network behind a TLS proxy has its CA there, not in the new root
HOST_CA=${SPIEL_HOST_CA:-/etc/ssl/certs/ca-certificates.crt}
in_root() { chroot "$ROOT" /usr/bin/env -i HOME=/root PATH=/opt/venv/bin:/usr/bin:/bin \
    PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_DEFAULT_TIMEOUT=180 PIP_CERT=/etc/ssl/host-ca.crt "$@"; }

mount_root() {
    mountpoint -q "$ROOT/proc" || mount -t proc proc "$ROOT/proc"
    mountpoint -q "$ROOT/dev" || mount --bind /dev "$ROOT/dev"
    mountpoint -q "$ROOT/sys" || mount --bind /sys "$ROOT/sys"
    cp /etc/resolv.conf "$ROOT/etc/resolv.conf"
    cp "$HOST_CA" "$ROOT/etc/ssl/host-ca.crt"
}

install_checkout() {
    step "copying the checkout and installing it with [test] (pip under emulation)"
    mount_root
    rm -rf "$ROOT/src" && mkdir -p "$ROOT/src"
    tar -C "$REPO" --exclude=.git --exclude=.venv --exclude='__pycache__' --exclude='*.egg-info' \
        --exclude=build -cf - . | tar -C "$ROOT/src" -xf -
    # pip, not python: a venv whose ensurepip failed has python but no pip (seen once)
    [ -e "$ROOT/opt/venv/bin/pip" ] || { rm -rf "$ROOT/opt/venv" && in_root python3 -m venv /opt/venv; }
    [ -e "$ROOT/opt/venv/bin/pip" ] || die "python3 -m venv /opt/venv made no pip in the arm64 root"
    # --only-binary for the dependencies: a missing aarch64 wheel fails here instead of
    # silently building from source (the project itself is built from the checkout)
    in_root sh -c 'cd /src && pip install -q --only-binary=:all: --no-binary=spiel-edge ".[test]"'
    in_root python -c 'import platform, sys; print("arm64 root:", platform.machine(), sys.version.split()[0])'
    in_root pip list --format=freeze | grep -i -E '^(numpy|numba|onnxruntime|mcap|pyserial|crc32c|libusb-package)=' || true
}

run_tests() {
    step "core and framing tests under emulation, on the installed package"
    # The tests run from a copy of tests/ and tools/ (no package), so they import the installed package and
    # reuse the kernels `run` compiled into its cache (a checkout on sys.path would compile
    # them all again: about 30 min under emulation). The cold-cache test is left out: it
    # compiles every kernel twice in a subprocess with a 600 s limit, which emulation exceeds.
    in_root sh -c 'rm -rf /srctests && mkdir /srctests && cp -r /src/tests /src/tools /src/pyproject.toml /srctests/ &&
        cd /srctests && python -m pytest -q -p no:cacheprovider tests/core tests/protocol/test_proto_vectors.py \
        tests/protocol/test_proto_cobs.py tests/protocol/test_proto_framing.py \
        --deselect tests/core/test_numba_cache.py::test_second_start_loads_every_kernel_from_the_cache' \
        | tail -5
}

compare_positions() {
    step "spiel-edge run --port sim:// ($FRAMES acquisitions) on arm64 and on the host"
    local url='sim://smoke?scene=replay'
    rm -f "$ROOT/tmp/arm64.ndjson" "$WORK/host.ndjson"  # outputs never overwrite: a rerun starts clean
    in_root sh -c "cd /tmp && spiel-edge run --port '$url' --frames $FRAMES --rate 0 -o /tmp/arm64.ndjson"
    local host_py=${SPIEL_HOST_PYTHON:-$REPO/.venv/bin/python}
    (cd "$REPO" && "$(dirname "$host_py")/spiel-edge" run --port "$url" --frames "$FRAMES" --rate 0 \
        -o "$WORK/host.ndjson")
    "$host_py" -m tools.release.compare_ndjson_positions "$WORK/host.ndjson" "$ROOT/tmp/arm64.ndjson" \
        --tolerance-mm 0.01
    step "the same run again on arm64, warm: every kernel and numba's runtime from the cache"
    rm -f "$ROOT/tmp/arm64-warm.ndjson"
    in_root sh -c "cd /tmp && spiel-edge run --port '$url' --frames $FRAMES --rate 0 -o /tmp/arm64-warm.ndjson"
    find "$ROOT/opt/venv" -name 'spiel_edge-nrt-*.nbo' | grep -q . || die "no numba runtime cache file"
    "$host_py" -m tools.release.compare_ndjson_positions "$WORK/host.ndjson" "$ROOT/tmp/arm64-warm.ndjson" \
        --tolerance-mm 0.01
}

fetch_qemu
register_binfmt
make_root
if [ "${SPIEL_SMOKE_ROOT_ONLY:-0}" = 1 ]; then step "arm64 root ready"; exit 0; fi
if [ -n "${SPIEL_SMOKE_EXEC:-}" ]; then
    mount_root
    step "running on the host with the arm64 root ready: $SPIEL_SMOKE_EXEC"
    ARM_ROOT=$ROOT bash -c "$SPIEL_SMOKE_EXEC"
    step "done"
    exit 0
fi
install_checkout
compare_positions
run_tests
step "aarch64 smoke test passed"
