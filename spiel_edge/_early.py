"""Signals from the first instruction of the ``spiel-edge`` command: imported by the package's
``__init__`` only when the process is the command itself (the console script, or
``python -m spiel_edge.cli``), before any slow import. INT, TERM and HUP are recorded here;
``spiel_edge.cli.main`` turns a recorded one into its documented status (130) instead of
the process dying by the signal (TERM, HUP) or with a traceback (INT) while it loads.
Imported as a library, spiel-edge installs nothing."""

from __future__ import annotations

import signal

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
received: list[int] = []


def _record(signum: int, frame: object) -> None:
    received.append(signum)


for _sig in SIGNALS:
    signal.signal(_sig, _record)
