"""The command line's signal handling (the one place that installs handlers): INT, TERM and
HUP end a session cleanly, so every output is finalized."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """TERM or HUP, raised like Ctrl-C so the same clean-up (finally, context managers) runs."""


@contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[threading.Event]:
    """Set ``stop`` on the first signal; a second SIGINT interrupts at once. Handlers are only
    installed in the main thread (elsewhere the caller sets ``stop`` itself)."""

    def handler(signum: int, frame: object) -> None:
        if stop.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        stop.set()

    with _handling(STOP_SIGNALS, handler):
        yield stop


@contextmanager
def terminate_raises() -> Iterator[None]:
    """Inside the block TERM and HUP raise :class:`Terminated` (INT raises KeyboardInterrupt as
    always): for commands without a stop loop, whose finally blocks close the outputs."""

    def handler(signum: int, frame: object) -> None:
        raise Terminated(f"signal {signum}")

    with _handling((signal.SIGTERM, signal.SIGHUP), handler):
        yield


@contextmanager
def _handling(signals: tuple[int, ...], handler) -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
