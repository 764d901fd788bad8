"""Serve the virtual board on a pseudo-terminal, so ``--port /dev/pts/N`` runs the real
serial code path (termios, exclusive lock, EIO on unplug) of a CDC-ACM board.

The server owns the pty master. An unplug closes it (the host's reads fail with EIO, as
when a USB board is pulled) and opens a new pty when the board comes back; its path is
announced again, and the optional ``link`` symlink (like a udev ``/dev/spiel-*`` rule) is
moved to it so that a host reopening the symlink finds the board wherever it is.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import select
import termios
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

from spiel_edge.errors import ConfigError
from spiel_edge.link.sim_options import SimOptions
from spiel_edge.safety.guard import shorten
from spiel_edge.sim.device import DeviceGone, SimDevice

log = logging.getLogger(__name__)

CHUNK = 65536
MIN_WAIT_S = 0.0002


class _Pty:
    """One pty pair; the server keeps the slave open too, so the pty lives until unplug."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    def unread(self) -> int:
        """Bytes written to the host that it has not read yet."""
        buf = fcntl.ioctl(self.slave, termios.FIONREAD, b"\0\0\0\0")
        return int.from_bytes(buf, "little")

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def check_link_path(link: str) -> None:
    """The --link path may be a symlink (ours, from an earlier run) or nothing: never a file
    or folder, which replacing it would destroy."""
    if os.path.lexists(link) and not os.path.islink(link):
        raise ConfigError(f"--link {shorten(link)}: exists and is not a symlink; not replacing it")


def _point_link(link: str | None, target: str) -> None:
    if not link:
        return
    tmp = f"{link}.tmp{os.getpid()}"
    if os.path.lexists(tmp):
        os.unlink(tmp)
    os.symlink(target, tmp)
    os.replace(tmp, link)


class PtyServer:
    """``serve(stop)`` until ``stop`` is set; ``announce(path)`` is called for every pty."""

    def __init__(
        self, device: SimDevice, *, link: str | None = None, announce: Callable[[str], None] = print
    ):
        self.device = device
        self.link = link
        self.announce = announce
        self.pty: _Pty | None = None

    def serve(self, stop: threading.Event) -> None:
        try:
            while not stop.is_set():
                if self.pty is None and not self._plug_in(stop):
                    continue
                self._step()
        finally:
            if self.pty is not None:
                self.pty.close()
            if self.link and os.path.islink(self.link):
                os.unlink(self.link)

    def _plug_in(self, stop: threading.Event) -> bool:
        device = self.device
        now = device.clock()
        device.update(now)
        if not device.plugged:
            stop.wait(max(device.next_event(now) - now, MIN_WAIT_S))
            return False
        self.pty = _Pty()
        device.drained = lambda: self.pty is not None and self.pty.unread() == 0
        _point_link(self.link, self.pty.path)
        self.announce(self.pty.path)
        return True

    def _unplug(self) -> None:
        assert self.pty is not None
        log.info("unplugged: closing %s", self.pty.path)
        self.pty.close()
        self.pty = None

    def _step(self) -> None:
        pty, device = self.pty, self.device
        assert pty is not None
        now = device.clock()
        try:
            waiting = device.pending()
        except DeviceGone:
            self._unplug()
            return
        wait = max(device.next_event(now) - now, MIN_WAIT_S)
        writers = [pty.master] if waiting else []
        readable, writable, _ = select.select([pty.master], writers, [], wait)
        try:
            if readable:
                self._from_host(pty)
            if writable or not waiting:
                self._to_host(pty)
        except DeviceGone:
            self._unplug()

    def _from_host(self, pty: _Pty) -> None:
        try:
            data = os.read(pty.master, CHUNK)
        except BlockingIOError:
            return
        except OSError as exc:  # EIO: no process has the slave open, nothing to read
            if exc.errno != errno.EIO:
                raise
            time.sleep(0.001)
            return
        if data:
            self.device.write(data)

    def _to_host(self, pty: _Pty) -> None:
        data = self.device.peek(CHUNK)
        if not data:
            return
        try:
            written = os.write(pty.master, data)
        except BlockingIOError:
            written = 0
        self.device.consume(written)


def serve_pty(
    url: str = "sim://",
    *,
    link: str | None = None,
    stop: threading.Event | None = None,
    announce: Callable[[str], None] = print,
) -> SimDevice:
    """Run a virtual board from ``url``'s options on a pty until ``stop`` is set."""
    device = SimDevice(SimOptions.from_url(url))
    if link:
        check_link_path(link)
        Path(link).parent.mkdir(parents=True, exist_ok=True)
    PtyServer(device, link=link, announce=announce).serve(stop or threading.Event())
    return device
