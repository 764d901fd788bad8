"""The mps2-an386 firmware under qemu-system-arm, for tests and tools.

``build_mps2(out_dir)`` builds ``firmware.elf`` with the firmware's Makefile (``make TARGET=mps2``)
and returns its path, or raises :class:`Unavailable` naming what is missing (the tests turn it
into a skip). :class:`QemuBoard` boots an image on a pty with its flash in a host file: qemu
maps the board's PSRAM, where the target keeps its flash, onto that file (a
``memory-backend-file`` with ``share=on``), so the flash outlives a kill and a restart of qemu
exactly as the board wrote it. The same file holds the target's power-cut mailbox
(``targets/mps2-an386/nor_mps2.c``): :meth:`QemuBoard.arm` makes the n-th flash operation stop
the board half done (counted from the arming, across resets: the boot stage's record writes
count too). ``firmware.elf`` is the boot stage with the built-in application; ``app.bin`` beside
it is the application image that ``spiel-edge firmware pack --target mps2-an386`` wraps.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import struct
import subprocess
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FIRMWARE = REPO / "firmware_protocol" / "firmware"
QEMU = "qemu-system-arm"
ARM_CC = "arm-none-eabi-gcc"
PSRAM_SIZE = 16 << 20  # the machine's RAM: the file must be exactly this long
FLASH_SIZE = 64 << 10  # mps2.h: CFG_FLASH_SIZE, the config store at file offset 0
# mps2.h: the boot record's two sectors at 0x10000, image slots 0 and 1 at 0x100000 and
# 0x200000 (1 MiB each): erased (0xFF) up to PERSISTENT_END in a new flash file
SLOT_SIZE = 1 << 20
SLOT0, BOOT_RECORD = 0x100000, 0x10000
PERSISTENT_END = SLOT0 + 2 * SLOT_SIZE
MAILBOX = 0x00F00000  # mps2.h: FI_OFF
SEED = 0x00F01000  # mps2.h: SEED_OFF, hal_random's state
MAILBOX_MAGIC = 0x49465053
CUT, FAIL = 1, 2


class Unavailable(Exception):
    """A tool the target needs is not installed (the message names the Debian package)."""


def missing_tools() -> str | None:
    need = {
        "make": "make",
        ARM_CC: "gcc-arm-none-eabi and libnewlib-arm-none-eabi",
        QEMU: "qemu-system-arm",
    }
    for tool, package in need.items():
        if shutil.which(tool) is None:
            return f"{tool} not found (Debian: apt-get install {package})"
    return None


def build_mps2(out_dir: Path, target: str = "mps2", extra: tuple[str, ...] = ()) -> Path:
    """``make TARGET=<target> BUILD=<out_dir>`` in the firmware folder; the image's path."""
    why = missing_tools()
    if why:
        raise Unavailable(why)
    build = Path(out_dir) / target
    cmd = ["make", "-s", f"TARGET={target}", f"BUILD={build}", *extra]
    done = subprocess.run(cmd, cwd=FIRMWARE, capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        if "nano.specs" in done.stderr or "newlib" in done.stderr:
            raise Unavailable(
                "newlib-nano missing (Debian: apt-get install libnewlib-arm-none-eabi)"
            )
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stdout}\n{done.stderr}")
    return build / "firmware.elf"


def new_flash(path: Path) -> Path:
    """An erased flash (0xFF: config store, boot record, image slots) in a PSRAM-sized file,
    mailbox disarmed."""
    with open(path, "wb") as f:
        f.write(b"\xff" * PERSISTENT_END)
        f.truncate(PSRAM_SIZE)
    return path


def app_bin(elf: Path) -> Path:
    """The application's flat image beside ``firmware.elf`` (what ``firmware pack`` wraps)."""
    return Path(elf).with_name("app.bin")


class QemuBoard:
    """One qemu process running ``elf`` with ``flash`` as its PSRAM; ``port`` is its pty."""

    def __init__(self, elf: Path, flash: Path) -> None:
        self.elf, self.flash = Path(elf), Path(flash)
        self.proc: subprocess.Popen | None = None
        self.port = ""
        self._slave = -1

    def start(self, timeout_s: float = 10.0) -> str:
        cmd = [
            QEMU,
            "-M",
            "mps2-an386,memory-backend=psram",
            "-object",
            f"memory-backend-file,id=psram,size={PSRAM_SIZE},mem-path={self.flash},share=on",
            "-display",
            "none",
            "-monitor",
            "none",
            "-chardev",
            "pty,id=uart0",
            "-serial",
            "chardev:uart0",
            "-kernel",
            str(self.elf),
        ]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
        )
        line = b""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()  # "char device redirected to /dev/pts/N ..."
            if not line or b"redirected to" in line:
                break
        found = re.search(rb"(/dev/pts/\d+)", line)
        if not found:
            err = self.proc.stderr.read().decode(errors="replace") if self.proc.poll() else ""
            self.kill()
            raise RuntimeError(f"qemu did not report its pty: {line!r} {err}")
        self.port = found.group(1).decode()
        time.sleep(0.2)  # qemu names the pty before it loads the image
        if self.proc.poll() is not None:
            err = self.proc.stderr.read().decode(errors="replace")
            self.kill()
            raise RuntimeError(f"qemu stopped at start: {err.strip()}")
        # hold the pty's slave open, as a USB CDC port stays while the board is powered:
        # qemu then never sees a hang-up between two host commands
        self._slave = os.open(self.port, os.O_RDWR | os.O_NOCTTY)
        return self.port

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        """Pull the power: SIGKILL, nothing is flushed but what the board already stored."""
        if self._slave >= 0:
            os.close(self._slave)
            self._slave = -1
        if self.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
            for stream in (self.proc.stdout, self.proc.stderr):
                stream.close()
            self.proc = None

    def restart(self) -> str:
        self.kill()
        return self.start()

    # ---- the power-cut mailbox ----------------------------------------------------------

    def arm(self, mode: int, at: int) -> None:
        """Before start(): the flash operation number ``at`` (0-based, counted from now across
        resets) is cut in half and the board stops (CUT), or fails (FAIL); once."""
        with open(self.flash, "r+b") as f:
            f.seek(MAILBOX)
            f.write(struct.pack("<5I", MAILBOX_MAGIC, mode, at, 0, 0))

    def disarm(self) -> None:
        with open(self.flash, "r+b") as f:
            f.seek(MAILBOX)
            f.write(bytes(20))

    def mailbox(self) -> dict[str, int]:
        with open(self.flash, "rb") as f:
            f.seek(MAILBOX)
            magic, mode, at, ops, fired = struct.unpack("<5I", f.read(20))
        return {"armed": magic == MAILBOX_MAGIC, "mode": mode, "at": at, "ops": ops, "fired": fired}

    def flash_bytes(self) -> bytes:
        with open(self.flash, "rb") as f:
            return f.read(FLASH_SIZE)

    def __enter__(self) -> QemuBoard:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.kill()
