"""The RP2040 target (``targets/rp2040``) in the rp2040js emulator, for tests.

``build_rp2040(out_dir)`` runs ``make TARGET=rp2040`` and returns the emulator image
(``firmware-emu.uf2``), or raises :class:`Unavailable` naming what is missing (the tests turn it
into a skip). :class:`Rp2040Board` starts ``run-emulated.sh`` (its first stdout line is the pty),
keeps the emulator's messages in a file, and stops it with SIGTERM, waiting until it is gone:
the emulator keeps a core busy, so no test may leave one running.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FIRMWARE = REPO / "firmware_protocol" / "firmware"
TARGET_DIR = FIRMWARE / "targets" / "rp2040"
RUN = TARGET_DIR / "run-emulated.sh"
RP2040JS = TARGET_DIR / "emu" / "node_modules" / "rp2040js"


class Unavailable(Exception):
    """A tool the target or its emulator needs is not installed."""


def missing_tools() -> str | None:
    need = {
        "make": "make",
        "arm-none-eabi-gcc": "gcc-arm-none-eabi and libnewlib-arm-none-eabi (Debian)",
        "node": "nodejs (Debian)",
        "socat": "socat (Debian)",
    }
    for tool, package in need.items():
        if shutil.which(tool) is None:
            return f"{tool} not found (install {package})"
    if not RP2040JS.is_dir():
        return (
            "rp2040js not installed (.ci/run installs it: "
            f"npm install --prefix {TARGET_DIR / 'emu'})"
        )
    return None


def build_rp2040(out_dir: Path, extra: tuple[str, ...] = ()) -> Path:
    """``make TARGET=rp2040 BUILD=<out_dir>/rp2040``; the emulator image's path."""
    why = missing_tools()
    if why:
        raise Unavailable(why)
    build = Path(out_dir) / "rp2040"
    cmd = ["make", "-s", "TARGET=rp2040", f"BUILD={build}", *extra]
    done = subprocess.run(cmd, cwd=FIRMWARE, capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        if "nano.specs" in done.stderr:
            raise Unavailable("newlib-nano missing (Debian: libnewlib-arm-none-eabi)")
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stdout}\n{done.stderr}")
    return build / "firmware-emu.uf2"


class Rp2040Board:
    """One emulated Pico running ``image``; ``port`` is its USB CDC port (a pty)."""

    def __init__(self, image: Path, log: Path, env: dict[str, str] | None = None) -> None:
        self.image, self.log = Path(image), Path(log)
        self.env = env  # added to this process's environment (run.mjs: RP2040_EMU_*)
        self.proc: subprocess.Popen | None = None
        self.port = ""

    def start(self, timeout_s: float = 60.0) -> Rp2040Board:
        with open(self.log, "ab") as err:
            self.proc = subprocess.Popen(
                [str(RUN), str(self.image)],
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
                env=None if self.env is None else {**os.environ, **self.env},
            )
        line = self.proc.stdout.readline().strip()  # the script waits at most 5 s for socat
        if not line.endswith("/tty"):
            self.stop()
            raise RuntimeError(f"run-emulated.sh gave no pty: {line!r} {self.messages()}")
        self.port = line
        # the boot stage checks the image's SHA-256 before the application starts USB: a few
        # seconds of the emulated M0+ for the full build
        self.wait_message("USB configured", timeout_s=timeout_s)
        return self

    def messages(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def wait_message(self, text: str, count: int = 1, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self.messages().count(text) < count:
            if time.monotonic() > deadline:
                raise AssertionError(f"no {text!r} x{count} from the emulator: {self.messages()}")
            time.sleep(0.05)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc.stdout.close()
        self.proc = None

    def __enter__(self) -> Rp2040Board:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
