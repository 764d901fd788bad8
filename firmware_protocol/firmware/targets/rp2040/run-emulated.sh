#!/usr/bin/env bash
# run-emulated.sh [IMAGE]: the RP2040 target in the rp2040js emulator, its USB CDC port on a pty.
# IMAGE (.uf2 or .bin) defaults to what `make -C firmware_protocol/firmware TARGET=rp2040` built
# for the emulator (build/rp2040/firmware-emu.uf2). Prints the pty's path as its first line on
# stdout, then runs until SIGTERM/SIGINT or until its caller exits (the emulator keeps a core
# busy: it must never outlive the test or shell that started it). The emulator's own messages
# (each boot, the USB configuration) go to stderr.
# Needs node, socat and rp2040js in emu/node_modules (.ci/run installs it: npm install --prefix
# emu); installs nothing.
set -u
here="$(cd "$(dirname "$0")" && pwd)"
image="${1:-$here/../../build/rp2040/firmware-emu.uf2}"
caller=$PPID
for tool in node socat; do
  command -v "$tool" >/dev/null 2>&1 || { echo "run-emulated.sh: $tool not found" >&2; exit 3; }
done
[ -d "$here/emu/node_modules/rp2040js" ] || {
  echo "run-emulated.sh: rp2040js not installed (npm install --prefix $here/emu)" >&2; exit 3; }
[ -f "$image" ] || { echo "run-emulated.sh: no image $image (make TARGET=rp2040)" >&2; exit 3; }
image="$(cd "$(dirname "$image")" && pwd)/$(basename "$image")"
dir="$(mktemp -d "${TMPDIR:-/tmp}/rp2040-emu.XXXXXX")"
cleanup() {
  [ -n "${socat_pid:-}" ] && kill "$socat_pid" 2>/dev/null
  [ -n "${socat_pid:-}" ] && wait "$socat_pid" 2>/dev/null
  rm -rf "$dir"
}
trap 'cleanup; exit 0' TERM INT HUP
trap cleanup EXIT
# socat owns the pty and runs the emulator on its other side; node leaves when its stdin closes
socat PTY,link="$dir/tty",raw,echo=0 \
  EXEC:"node $here/emu/run.mjs $image",nofork &
socat_pid=$!
for _ in $(seq 1 100); do
  [ -e "$dir/tty" ] && break
  kill -0 "$socat_pid" 2>/dev/null || exit 1
  sleep 0.05
done
[ -e "$dir/tty" ] || { echo "run-emulated.sh: socat made no pty" >&2; exit 1; }
# the link, not the /dev/pts name it points to: a pty number freed by a crash is soon another
# program's, the link dies with this emulator
echo "$dir/tty"
# stay while the caller and socat live; sleep in short steps so a TERM is handled at once
while kill -0 "$caller" 2>/dev/null && kill -0 "$socat_pid" 2>/dev/null; do
  sleep 0.2 & wait $!
done
