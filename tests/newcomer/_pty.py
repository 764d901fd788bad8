"""The virtual board served on a pseudo-terminal (``spiel-edge simulate --pty``) for a test."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from pathlib import Path


@contextlib.contextmanager
def pty_board(link: Path, url: str = "sim://", timeout_s: float = 60.0):
    """Yields the process once ``link`` points at its pty; stops it afterwards. The process's
    stderr is kept in ``proc.stderr_text`` after the block."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "spiel_edge.cli", "simulate", "--pty", url, "--link", str(link)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + timeout_s
        while not link.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.exists(), "the virtual board did not come up"
        yield proc
    finally:
        proc.terminate()
        _out, proc.stderr_text = proc.communicate(timeout=10)
