"""Serial links through pyserial: device paths, ``serial://PATH`` and ``sim://`` URLs.

``sim://`` is served by :mod:`spiel_edge.sim.protocol_sim` through pyserial's URL-handler
mechanism, so the virtual board runs this exact code path. pyserial reports an unplugged
device as SerialException from read/write but as a bare OSError(EIO) from ``in_waiting``:
both become DeviceDisconnectedError.
"""

from __future__ import annotations

import errno
import logging
import os
import select

import serial
import serial.tools.list_ports

from spiel_edge.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError
from spiel_edge.link import LinkIdentity

log = logging.getLogger(__name__)

SIM_HANDLER_PACKAGE = "spiel_edge.sim"
WRITE_TIMEOUT_S = 1.0  # a board that does not drain 1 s of output is stalled or gone
_ABSENT = {errno.ENOENT, errno.ENODEV, errno.ENXIO, errno.EIO}
# bytes per read of a posix port: what one read returns shares one arrival time, so this
# bounds how long an acquisition can wait behind others read with it (about 12 acquisitions
# of 4 x 64 samples; docs/first-start.md, "Latency at --rate 0")
READ_MAX = 8192


def _register_sim_handler() -> None:
    if SIM_HANDLER_PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(SIM_HANDLER_PACKAGE)


def device_path(url: str) -> str:
    """The pyserial port name of a URL: ``serial://PATH`` -> PATH, others unchanged."""
    return url[len("serial://") :] if url.lower().startswith("serial://") else url


class SerialLink:
    """A pyserial port as a Link; ``read`` returns as soon as any bytes are there."""

    def __init__(self, url: str, port: serial.SerialBase):
        self.url = url
        self._port = port
        self._timeout: float | None = None
        # a posix device or pty: select and os.read on its descriptor (pyserial's read loop
        # costs as much per call as decoding the frames it returns)
        fd = getattr(port, "fd", None)
        self._fd = (
            fd if isinstance(fd, int) and type(port).__module__ == "serial.serialposix" else None
        )

    def read(self, timeout_s: float) -> bytes:
        if self._fd is not None:
            return self._read_fd(self._fd, timeout_s)
        port = self._port
        try:
            waiting = port.in_waiting
            if waiting:
                return port.read(min(waiting, READ_MAX))
            if self._timeout != timeout_s:
                port.timeout = self._timeout = timeout_s
            data = port.read(1)
            if data:
                waiting = port.in_waiting
                if waiting:
                    data += port.read(min(waiting, READ_MAX - 1))
            return data
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnectedError(f"{self.url}: link lost: {exc}") from exc

    def _read_fd(self, fd: int, timeout_s: float) -> bytes:
        """What the descriptor holds (at most READ_MAX bytes), waiting up to ``timeout_s``
        for the first; b"" on a timeout. Readable with nothing to read is an unplug, as
        pyserial treats it."""
        try:
            ready, _, _ = select.select([fd], [], [], timeout_s)
            if not ready:
                return b""
            data = os.read(fd, READ_MAX)
        except BlockingIOError:
            return b""
        except (OSError, ValueError) as exc:  # ValueError: the port was closed meanwhile
            raise DeviceDisconnectedError(f"{self.url}: link lost: {exc}") from exc
        if not data:
            raise DeviceDisconnectedError(f"{self.url}: link lost: the device returned no data")
        return data

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeoutError(f"{self.url}: the board stopped taking data ({exc})") from exc
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnectedError(f"{self.url}: link lost: {exc}") from exc

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError) as exc:  # closing a vanished device
            log.debug("%s: close: %s", self.url, exc)

    def identity(self) -> LinkIdentity:
        path = device_path(self.url)
        for info in serial.tools.list_ports.comports():
            if path in (info.device, getattr(info, "device_path", None)) and info.vid is not None:
                return LinkIdentity(self.url, info.vid, info.pid, info.serial_number)
        return LinkIdentity(self.url)


def open_serial(url: str, *, exclusive: bool = True) -> SerialLink:
    """Open a serial device or a ``sim://`` URL; a missing device raises
    DeviceDisconnectedError (it may appear later), other failures DeviceError with a hint."""
    _register_sim_handler()
    path = device_path(url)
    try:
        port = serial.serial_for_url(
            path, baudrate=115200, timeout=0.1, write_timeout=WRITE_TIMEOUT_S, exclusive=exclusive
        )
    except ValueError as exc:  # pyserial: bad URL or option
        raise DeviceError(f"{url}: {exc}") from exc
    except (serial.SerialException, OSError) as exc:
        raise _open_error(url, exc) from exc
    return SerialLink(url, port)


def _open_error(url: str, exc: Exception) -> DeviceError:
    code = getattr(exc, "errno", None)
    text = str(exc)
    if code == errno.EACCES or "Permission denied" in text:
        return DeviceError(
            f"{url}: permission denied; add your user to the 'dialout' group or install the "
            "udev rule from the README, then log in again"
        )
    if "exclusively lock" in text or code == errno.EBUSY:
        return DeviceError(f"{url}: the port is in use by another process")
    if code in _ABSENT or "No such file" in text or "could not open port" in text:
        return DeviceDisconnectedError(f"{url}: no such device ({text})")
    return DeviceError(f"{url}: cannot open: {text}")
