"""Build and run the C reference firmware (firmware_protocol/firmware) for the tests.

Two builds, both through the firmware's Makefile (its release flags: every warning an error,
-O2) with the system C compiler:
* the posix target (``spiel_fw_posix``): the firmware as a Linux program on a pty, A-scans
  from a scans file (tools/release/firmware_scans.py), flash in a file;
* the core driver (tests/firmware/core_driver.c): the portable core with an in-memory HAL,
  fed request bytes on stdin, for exact request/response transcripts.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import shutil
import signal
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "firmware_protocol" / "firmware"
PROTO = ROOT / "firmware_protocol" / "c"
DRIVER = Path(__file__).with_name("core_driver.c")
# SPIEL_FW_SANITIZE=1: every build of these tests with AddressSanitizer and UBSan (the Makefile's
# SANITIZE=1; the first report aborts the firmware, which the tests see as a dead board)
VENDOR = FIRMWARE / "vendor" / "monocypher"
DEV_PUB = FIRMWARE / "keys" / "dev.pub"  # the key boards built here trust (FW_KEY)
# the defines the Makefile has a switch for (make VAR=0|1); any other goes in CFLAGS_EXTRA
SWITCHES = {
    "SPIEL_FW_UPDATE": "FW_UPDATE",
    "SPIEL_FW_EXEC_COPY": "FW_EXEC_COPY",
    "SPIEL_IQ_SAMPLES": "IQ_SAMPLES",
}


def compiler() -> str:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    raise RuntimeError("no C compiler (cc, gcc or clang): the posix firmware tests need one")


def make(build: Path, target: str, defines: dict, key: Path | None = None, *extra: str) -> None:
    """``make TARGET=target BUILD=build`` in the firmware folder: the Makefile's release flags
    (its warnings as errors, -O2), the defines as its switches or CFLAGS_EXTRA."""
    if shutil.which("make") is None:
        raise RuntimeError("no make: the firmware tests build through the firmware's Makefile")
    args = [f"{SWITCHES[k]}={v}" for k, v in defines.items() if k in SWITCHES]
    cflags = " ".join(f"-D{k}={v}" for k, v in sorted(defines.items()) if k not in SWITCHES)
    if os.environ.get("SPIEL_FW_SANITIZE") == "1":
        args.append("SANITIZE=1")
    else:
        args.append("HOST_DEBUG=")  # the release flags without debug info: a faster build
    cmd = [
        "make",
        "-s",
        "-C",
        str(FIRMWARE),
        f"TARGET={target}",
        f"BUILD={build}",
        f"CC={compiler()}",
        f"FW_KEY={(key or DEV_PUB).resolve()}",
        *args,
        *extra,
    ]
    if cflags:
        cmd.append(f"CFLAGS_EXTRA={cflags}")
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    if done.returncode:
        raise RuntimeError(f"build failed: {' '.join(cmd)}\n{done.stderr}")


def _name(stem: str, defines: dict, key: Path | None) -> str:
    name = stem + "".join(f"_{k}{v}" for k, v in sorted(defines.items()))
    return name if key is None or Path(key) == DEV_PUB else f"{name}_{Path(key).stem}"


def build_posix(out_dir: Path, key: Path | None = None, **defines) -> Path:
    """The posix target, e.g. ``build_posix(d, SPIEL_MAX_PAYLOAD=256)``; with its firmware
    image slots (``--images DIR``) unless ``SPIEL_FW_UPDATE=0``, and I/Q streams (its recordings'
    amplitude as i, q = 0) unless ``SPIEL_IQ_SAMPLES=0``. ``key``: the public key file it
    trusts (default the development key). Built by ``make TARGET=posix`` into a folder of its
    own under out_dir (kept: a second call with the same defines builds nothing)."""
    defines = {"SPIEL_FW_UPDATE": 1, "SPIEL_FW_EXEC_COPY": 1, "SPIEL_IQ_SAMPLES": 1, **defines}
    build = Path(out_dir) / _name("posix", defines, key)
    make(build, "posix", defines, key)
    return build / "spiel_fw_posix"


def build_driver(out_dir: Path, **defines) -> Path:
    """The core under tests/firmware/core_driver.c (``make TARGET=driver``), without firmware
    update and I/Q unless the defines turn them on."""
    defines = {"SPIEL_FW_UPDATE": 0, "SPIEL_FW_EXEC_COPY": 0, "SPIEL_IQ_SAMPLES": 0, **defines}
    build = Path(out_dir) / _name("driver", defines, None)
    make(build, "driver", defines, None, f"DRIVER={DRIVER}")
    return build / "core_driver"


def build_test_driver(out_dir: Path, source: Path, with_: str) -> Path:
    """A test's own C driver (main() in ``source``) linked with the frame layer (``"proto"``) or
    the vendored Ed25519 verifier (``"ed25519"``): ``make TARGET=driver WITH=...``."""
    build = Path(out_dir) / f"{Path(source).stem}_{with_}"
    make(build, "driver", {}, None, f"DRIVER={Path(source).resolve()}", f"WITH={with_}")
    return build / Path(source).stem


class PosixBoard:
    """``with PosixBoard(exe, scans, flash) as board: board.port`` -> the pty path."""

    def __init__(self, exe: Path, scans: Path, flash: Path, *extra: str, serial: str = ""):
        self.args = [str(exe), "--pty", "--scans", str(scans), "--flash", str(flash), *extra]
        if serial:
            self.args += ["--serial", serial]
        self.proc: subprocess.Popen | None = None
        self.port = ""

    def start(self) -> PosixBoard:
        self.proc = subprocess.Popen(
            self.args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout=10):
            self.stop()
            raise RuntimeError("the posix firmware did not print its pty within 10 s")
        self.port = self.proc.stdout.readline().strip()
        if not self.port.startswith("/dev/"):
            err = self.proc.stderr.read() if self.proc.poll() is not None else ""
            self.stop()
            raise RuntimeError(f"the posix firmware failed to start: {self.port!r} {err}")
        return self

    def wait_dead(self, timeout: float = 10.0) -> int:
        """The exit status once the process ended (e.g. -9 after its own power cut)."""
        assert self.proc is not None
        return self.proc.wait(timeout)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGKILL)  # the process we started, by its id
            self.proc.wait(10)
        if self.proc is not None:
            for stream in (self.proc.stdout, self.proc.stderr):
                if stream:
                    stream.close()

    def __enter__(self) -> PosixBoard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class CoreDriver:
    """The core with an in-memory HAL (core_driver.c): ``feed(wire) -> bytes written``."""

    def __init__(self, exe: Path, scans: Path):
        self.proc = subprocess.Popen(
            [str(exe)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1
        )
        assert self.command(f"scans {scans}") == "ok"
        assert self.command("init") == "ok"

    def command(self, line: str) -> str:
        assert self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline().strip()
        if not answer:
            raise RuntimeError(f"core driver died on {line[:60]!r}")
        return answer

    def _out(self, answer: str) -> bytes:
        kind, _, hexed = answer.partition(" ")
        assert kind == "out", answer
        return b"" if hexed == "-" else bytes.fromhex(hexed)

    def feed(self, wire: bytes) -> bytes:
        return self._out(self.command(f"feed {wire.hex() or '-'}"))

    def poll(self, n: int = 1) -> bytes:
        return self._out(self.command(f"poll {n}"))

    def set_time(self, us: int) -> None:
        assert self.command(f"time {int(us)}") == "ok"

    def stats(self) -> dict[str, int]:
        names = [
            "frames",
            "crc",
            "cobs",
            "length",
            "oversize",
            "version",
            "flags",
            "requests",
            "repeated",
            "acquisitions_sent",
            "frames_sent",
            "overruns",
            "flash_errors",
        ]
        kind, *values = self.command("stats").split()
        assert kind == "stats"
        return dict(zip(names, map(int, values), strict=True))

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait(10)
        if self.proc.stdout:
            self.proc.stdout.close()


def wait_for(predicate, timeout: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} not reached within {timeout} s")
        time.sleep(0.01)
