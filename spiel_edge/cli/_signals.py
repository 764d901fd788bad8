"""The command line's signal handling (the one place that installs handlers): INT, TERM and
HUP end a session cleanly, so every output is finalized.

A command's loop sees the stop event and ends normally. When it cannot (its thread is blocked
writing to a stdout nobody reads), a watchdog runs the registered :class:`Finalizers` itself
within ``FINALIZE_WITHIN_S`` and ends the process: a signal never leaves a recording
unfinalized.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
GRACE_S = 0.4  # the loop's own chance to stop before the watchdog steps in
FINALIZE_WITHIN_S = 1.0


class Finalizers:
    """Callables that make outputs complete (close a recording, rename a file into place).

    Each runs at most once, whoever calls first: the command on its normal way out, or the
    watchdog when the command is stuck."""

    def __init__(self, exit_status: int = 0) -> None:
        self.exit_status = exit_status  # the watchdog's, when they all succeed
        self._pending: list[Callable[[], None]] = []
        self._lock = threading.Lock()

    def add(self, finalize: Callable[[], None]) -> None:
        with self._lock:
            self._pending.append(finalize)

    def run_all(self) -> bool:
        """True when every one succeeded."""
        with self._lock:
            pending, self._pending = self._pending, []
        ok = True
        for finalize in pending:
            try:
                finalize()
            except Exception as exc:  # finalize the others regardless
                log.error("finalizing an output failed: %s", exc)
                ok = False
        return ok


class Terminated(KeyboardInterrupt):
    """TERM or HUP, raised like Ctrl-C so the same clean-up (finally, context managers) runs."""


REDELIVER_S = 0.02  # a signal that came during an import is handled again this much later


_LLVMLITE = f"{os.sep}llvmlite{os.sep}"


def deferred_in_import(signum: int, frame: object) -> bool:
    """True when the signal came while the main thread was importing a module or inside
    llvmlite: raising there breaks the import (numba's C extension reported ``ImportError:
    numba._devicearray failed to import`` with the interrupt's traceback, status 2) or leaves
    a native LLVM object half disposed (a second Ctrl-C 0.3 s into a cold `run` ended in
    glibc's "double free", status -6), so the signal is sent again ``REDELIVER_S`` later,
    until it lands outside both."""
    while frame is not None:
        name = getattr(getattr(frame, "f_code", None), "co_filename", "")
        if name.startswith("<frozen importlib") or _LLVMLITE in name:
            timer = threading.Timer(REDELIVER_S, _resend, args=(signum,))
            timer.daemon = True
            timer.start()
            return True
        frame = frame.f_back  # type: ignore[attr-defined]
    return False


def _resend(signum: int) -> None:
    with suppress(OSError):
        os.kill(os.getpid(), signum)


def interrupted(exc: BaseException) -> bool:
    """An exception raised because of a signal: a KeyboardInterrupt anywhere in its chain (a
    library that wrapped the interrupt in its own error)."""
    seen = 0
    while exc is not None and seen < 50:
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return False


@contextmanager
def stop_on_signals(
    stop: threading.Event, finalizers: Finalizers | None = None
) -> Iterator[threading.Event]:
    """Set ``stop`` on the first signal; a second SIGINT interrupts at once. With
    ``finalizers``, a command still running ``GRACE_S`` after the signal has them run by a
    watchdog, which then ends the process (status 0 when they all succeeded, else 2).
    Handlers are only installed in the main thread (elsewhere the caller sets ``stop``)."""
    done = threading.Event()

    def handler(signum: int, frame: object) -> None:
        if stop.is_set() and signum == signal.SIGINT:
            if deferred_in_import(signum, frame):
                return
            raise KeyboardInterrupt
        if not stop.is_set() and finalizers is not None:
            threading.Thread(
                target=_watchdog, args=(done, finalizers), name="finalize-on-signal", daemon=True
            ).start()
        stop.set()

    try:
        with _handling(STOP_SIGNALS, handler):
            yield stop
    finally:
        done.set()


def _watchdog(done: threading.Event, finalizers: Finalizers) -> None:
    if done.wait(GRACE_S):
        return
    hard = threading.Timer(FINALIZE_WITHIN_S - GRACE_S, os._exit, args=(2,))
    hard.daemon = True
    hard.start()
    ok = finalizers.run_all()
    if done.is_set():  # the command got unstuck meanwhile and ends by itself
        hard.cancel()
        return
    _say(b"stopped by a signal: outputs finalized by the watchdog\n")
    os._exit(finalizers.exit_status if ok else 2)


def _say(message: bytes) -> None:
    """One line on stderr without the stream's lock (the stuck thread may hold it)."""
    with suppress(OSError):
        os.write(2, message)


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
