"""Running under systemd: sd_notify readiness and watchdog, SIGTERM handling, journald logs.

Pure socket code on ``$NOTIFY_SOCKET`` (no libsystemd dependency). Everything here is a
no-op outside systemd, so the run loop can call it unconditionally.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

_WARN_EVERY_S = 60.0
# syslog priorities for journald's "<N>" line prefix (sd-daemon(3)).
_PRIORITIES = ((logging.CRITICAL, 2), (logging.ERROR, 3), (logging.WARNING, 4), (logging.INFO, 6))


def notify(state: str, env: Mapping[str, str] | None = None) -> bool:
    """Send one sd_notify datagram (e.g. ``"READY=1"``); False when not under systemd or on error."""
    env = os.environ if env is None else env
    address = env.get("NOTIFY_SOCKET", "")
    if not address:
        return False
    if address[0] == "@":  # abstract namespace socket
        address = "\0" + address[1:]
    elif address[0] != "/":
        log.debug("unsupported NOTIFY_SOCKET %r", address)
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            # Never block the run loop: a full queue (the manager is busy) drops this message.
            sock.setblocking(False)
            sock.connect(address)
            sock.sendall(state.encode("utf-8"))
    except OSError as exc:
        _warn_rate_limited("sd_notify %r failed: %s", state.split("\n", 1)[0], exc)
        return False
    return True


_last_warning = [-float("inf")]


def _warn_rate_limited(fmt: str, *args: object) -> None:
    now = time.monotonic()
    if now - _last_warning[0] >= _WARN_EVERY_S:
        _last_warning[0] = now
        log.warning(fmt, *args)
    else:
        log.debug(fmt, *args)


def watchdog_interval_s(
    env: Mapping[str, str] | None = None, pid: int | None = None
) -> float | None:
    """Half of systemd's WatchdogSec (as sd_watchdog_enabled(3) advises), or None when off."""
    env = os.environ if env is None else env
    try:
        usec = int(env.get("WATCHDOG_USEC", "0"))
    except ValueError:
        return None
    owner = env.get("WATCHDOG_PID")
    if usec <= 0 or (owner and owner != str(os.getpid() if pid is None else pid)):
        return None
    return usec / 2e6


class Notifier:
    """READY once, WATCHDOG on progress (rate-limited), STATUS and STOPPING for systemctl status.

    Call :meth:`ping` after each processed acquisition: a stalled device or loop then stops
    the pings and systemd restarts the service.
    """

    def __init__(
        self, env: Mapping[str, str] | None = None, clock: Callable[[], float] = time.monotonic
    ):
        self._env = dict(os.environ if env is None else env)
        self.enabled = bool(self._env.get("NOTIFY_SOCKET"))
        self.interval_s = watchdog_interval_s(self._env) if self.enabled else None
        self._clock = clock
        self._last_ping = -float("inf")

    def ready(self, status: str | None = None) -> bool:
        self._last_ping = self._clock()
        return self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def ping(self) -> bool:
        """WATCHDOG=1 at most once per interval; True when a datagram went out."""
        if self.interval_s is None:
            return False
        now = self._clock()
        if now - self._last_ping < self.interval_s:
            return False
        self._last_ping = now
        return self._send("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self._send(f"STATUS={text}")

    def starting(self, text: str, extend_s: float = 120.0) -> bool:
        """Still starting (e.g. compiling kernels): STATUS, and the start timeout extended by
        ``extend_s`` from now (EXTEND_TIMEOUT_USEC), so a slow first start is not killed."""
        return self._send(f"STATUS={text}\nEXTEND_TIMEOUT_USEC={int(extend_s * 1e6)}")

    def stopping(self) -> bool:
        return self._send("STOPPING=1")

    def _send(self, state: str) -> bool:
        return self.enabled and notify(state, self._env)


def stderr_is_journal(env: Mapping[str, str] | None = None, fd: int = 2) -> bool:
    """True when ``fd`` is the journald stream systemd connected (JOURNAL_STREAM=dev:inode)."""
    env = os.environ if env is None else env
    try:
        dev, ino = (int(v) for v in env.get("JOURNAL_STREAM", "").split(":"))
        st = os.fstat(fd)
    except (ValueError, OSError):
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


class JournalFormatter(logging.Formatter):
    """``<prio>logger: message``: journald strips the prefix into the entry's priority, so
    ``journalctl -p warning`` works; it adds its own timestamps."""

    def __init__(self) -> None:
        super().__init__("%(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        prio = next((p for level, p in _PRIORITIES if record.levelno >= level), 7)
        text = super().format(record)
        # Continuation lines (tracebacks) keep the priority of their record.
        return "\n".join(f"<{prio}>{line}" for line in text.splitlines())
