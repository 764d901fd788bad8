"""Log lines driven by clients, rate-limited: a peer connecting and disconnecting in a loop
(Foxglove's WebSocket server logs two or three lines per client, Zenoh its transport errors)
must not flood the journal. Our own modules rate-limit their repeated warnings where they are
raised; this filter covers the libraries' lines (every logger outside ``spiel_edge``)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

BURST = 5  # lines of one logger and level let through per window
WINDOW_S = 60.0


class ClientLogLimiter(logging.Filter):
    """A handler filter: per (logger, level), BURST lines per WINDOW_S; the first line let
    through after a quiet spell says how many were held back."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, own: str = "spiel_edge"):
        super().__init__()
        self._clock = clock
        self._own = own
        self._windows: dict[tuple[str, int], list] = {}  # key -> [start, passed, held]

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name == self._own or record.name.startswith(self._own + "."):
            return True
        key = (record.name, record.levelno)
        now = self._clock()
        window = self._windows.get(key)
        if window is None or now - window[0] >= WINDOW_S:
            held = window[2] if window is not None else 0
            self._windows[key] = [now, 1, 0]
            if held:
                record.msg = f"{record.getMessage()} ({held} more such lines held back)"
                record.args = None
            return True
        if window[1] < BURST:
            window[1] += 1
            if window[1] == BURST:
                record.msg = (
                    f"{record.getMessage()} (more such lines held back for {WINDOW_S:.0f} s)"
                )
                record.args = None
            return True
        window[2] += 1
        return False
