"""Say what numba compiles while it compiles: a bar on a terminal, plain lines elsewhere.

``spiel_edge._kernel_cache`` reports each kernel it has to compile (its ``listeners``);
:class:`Progress` turns those reports, in this process or sent as JSON lines by a warm-up
child, into output on stderr: on a terminal one line redrawn in place (a bar, the count, the
kernel, the seconds so far), else (a pipe, the journal) one line per kernel compiled.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

BAR = 24
# seconds to compile every kernel on one x86-64 core of this project's CI machine (the first
# start's estimate; docs/performance.md, "First start"), and a Raspberry Pi 4 core's factor
FULL_COMPILE_S = 100.0
SLOWER_ON = {"aarch64": 3.0, "armv7l": 4.0}


def estimate_seconds(n_missing: int, n_total: int, machine: str) -> float:
    """About how long compiling ``n_missing`` of ``n_total`` kernels takes on ``machine``."""
    share = n_missing / max(n_total, 1)
    return FULL_COMPILE_S * share * SLOWER_ON.get(machine, 1.0)


def kernel_seconds() -> dict[str, float]:
    """Measured seconds to compile each kernel (with its callees cached) on one x86-64 core
    (``compile_times.json``, written from a cold compile's own reports: docs/first-start.md)."""
    import json
    from pathlib import Path

    try:
        table = json.loads((Path(__file__).parent / "compile_times.json").read_text())
        return {str(k): float(v) for k, v in table["seconds"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def estimate_for(names: list[str], machine: str | None = None) -> float:
    """About how long compiling the kernels ``names`` takes here: the measured time of each
    (the mean of the measured ones for a kernel not in the table), times the CPU's factor."""
    import platform

    table = kernel_seconds()
    mean = sum(table.values()) / len(table) if table else FULL_COMPILE_S / 100
    factor = SLOWER_ON.get(machine or platform.machine(), 1.0)
    return sum(table.get(n, mean) for n in names) * factor


def about(seconds: float) -> str:
    if seconds < 90:
        return f"about {max(10, round(seconds, -1)):.0f} s"
    low, high = seconds / 60 * 0.7, seconds / 60 * 1.5
    return f"about {max(1, round(low)):.0f}-{max(2, round(high)):.0f} min"


class Progress:
    """Show compile reports on ``stream``; ``total`` is how many kernels are expected."""

    def __init__(self, total: int, stream: TextIO | None = None, tty: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self._isatty() if tty is None else tty
        self.total = max(total, 1)
        self.done = 0  # kernels compiled (one with several signatures counts once)
        self._compiled: set[str] = set()
        self.t0 = time.perf_counter()
        self.current = ""
        self._drawn = False
        self.notifier = None  # a service.systemd.Notifier: STATUS and a longer start timeout

    def _isatty(self) -> bool:
        try:
            return self.stream.isatty()
        except (AttributeError, ValueError):
            return False

    def say(self, line: str) -> None:
        """A line of its own (the bar, if any, is redrawn below it)."""
        self._clear()
        self._write(line + "\n")
        self._draw()

    def __call__(self, event: str, name: str, detail: object) -> None:
        """A ``_kernel_cache`` listener."""
        short = name.split(".", 1)[-1]
        if event == "compile":
            self.current = short
            self._draw()
        elif event == "compiled":
            if name in self._compiled:  # another signature of a kernel counted: no new line
                return
            self._compiled.add(name)
            self.done = len(self._compiled)
            if self.notifier is not None:
                self.notifier.starting(f"compiling kernels: {self.done}/{self.total} ({short})")
            if self.tty:
                self._draw()
            else:
                self._write(
                    f"compiled {self.done}/{self.total}: {name} "
                    f"({float(detail):.1f} s, {self.elapsed():.0f} s so far)\n"
                )
        elif event == "warning":
            self.say(f"warning: {detail}")

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def finish(self, line: str | None = None) -> None:
        self._clear()
        if line:
            self._write(line + "\n")

    def _draw(self) -> None:
        if not self.tty:
            return
        shown = min(self.done, self.total)
        filled = BAR * shown // self.total
        bar = "#" * filled + "-" * (BAR - filled)
        text = f"[{bar}] {shown}/{self.total} {self.elapsed():4.0f} s  {self.current}"
        self._write("\r" + text[:100] + "\x1b[K")
        self._drawn = True

    def _clear(self) -> None:
        if self.tty and self._drawn:
            self._write("\r\x1b[K")
            self._drawn = False

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # a terminal that hung up: compiling goes on
            pass
