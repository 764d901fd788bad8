"""Build and run tests/protocol/sp_driver.c against the C reference in firmware_protocol/c."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

DRIVER = Path(__file__).with_name("sp_driver.c")
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2"]


def compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def c_dir() -> Path:
    return Path(__file__).resolve().parents[2] / "firmware_protocol" / "c"


def build(cc: str, exe: Path) -> subprocess.CompletedProcess:
    """The driver over the frame layer. In a checkout: through the firmware's Makefile
    (``make TARGET=driver WITH=proto``, its release flags); an installed package without the
    firmware sources: the compiler alone with CFLAGS."""
    makefile = c_dir().parent / "firmware" / "Makefile"
    if makefile.is_file() and shutil.which("make"):
        build_dir = exe.parent / "build"
        cmd = [
            "make",
            "-s",
            "-C",
            str(makefile.parent),
            "TARGET=driver",
            "WITH=proto",
            f"BUILD={build_dir}",
            f"CC={cc}",
            f"DRIVER={DRIVER.resolve()}",
        ]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode == 0:
            shutil.copyfile(build_dir / DRIVER.stem, exe)
            exe.chmod(0o755)
        return done
    sources = sorted(str(p) for p in c_dir().glob("*.c"))
    cmd = [cc, *CFLAGS, f"-I{c_dir()}", *sources, str(DRIVER), "-o", str(exe)]
    return subprocess.run(cmd, capture_output=True, text=True)


def run(driver: Path, commands: list[str]) -> list[str]:
    out = subprocess.run(
        [str(driver)],
        input="\n".join(commands) + "\n",
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return out.stdout.splitlines()


def hx(data: bytes) -> str:
    return data.hex() or "-"
