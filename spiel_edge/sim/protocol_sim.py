"""pyserial URL handler for ``sim://``: the virtual board in-process, as a serial port.

pyserial imports ``<package>.protocol_sim`` for ``sim://`` URLs once ``spiel_edge.sim`` is in
``serial.protocol_handler_packages`` (:func:`spiel_edge.link.serial_link.open_serial` adds
it). Boards live in a per-process registry keyed by URL, so reopening the same URL after an
unplug finds the same board, as reopening /dev/ttyACM0 finds the same hardware. The port
behaves like a real one that was unplugged: read/write raise SerialException, ``in_waiting``
a bare OSError(EIO), open fails with ENOENT until the board is back.
"""

from __future__ import annotations

import errno
import threading
import time

from numpy.typing import ArrayLike
from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from spiel_edge.errors import ConfigError
from spiel_edge.link.sim_options import SimOptions
from spiel_edge.sim.device import DeviceGone, SimDevice
from spiel_edge.sim.scenes import EchoModelScene

_DEVICES: dict[str, SimDevice] = {}
_LOCK = threading.Lock()
MIN_SLEEP_S = 0.0002


def device_for_url(url: str) -> SimDevice:
    """The board behind ``url`` in this process (created on first use)."""
    with _LOCK:
        device = _DEVICES.get(url)
        if device is None:
            device = _DEVICES[url] = SimDevice(SimOptions.from_url(url))
        return device


def forget(url: str | None = None) -> None:
    """Drop one board (or all) from the registry: the next open builds a fresh one."""
    with _LOCK:
        if url is None:
            _DEVICES.clear()
        else:
            _DEVICES.pop(url, None)


def place_target(url: str, position_mm: ArrayLike) -> None:
    """Move the target of the model scene of the board behind ``url`` (``scene=model``) to
    ``position_mm`` (x, y, z); for tests that play the robot of a guided calibration."""
    scene = device_for_url(url).board.scene
    if not isinstance(scene, EchoModelScene):
        raise ConfigError(f"{url!r}: only the model scene (scene=model) has a target to move")
    scene.place(position_mm)


class Serial(SerialBase):
    """A serial port whose other end is a SimDevice."""

    def __init__(self, *args, **kwargs):
        self._device: SimDevice | None = None
        self._generation = 0
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        try:
            device = device_for_url(self.portstr)
        except ConfigError as exc:
            raise ValueError(str(exc)) from exc  # a bad URL, not an absent board
        device.update(device.clock())
        if not device.plugged:
            raise SerialException(
                errno.ENOENT, f"could not open port {self.portstr}: [Errno 2] No such device"
            )
        if self._exclusive and device.holder is not None:
            raise SerialException(errno.EBUSY, f"Could not exclusively lock port {self.portstr}")
        device.holder = self
        self._device, self._generation = device, device.generation
        self.is_open = True

    def close(self) -> None:
        device = self._device
        if device is not None and device.holder is self:
            device.holder = None
        self.is_open = False

    def _reconfigure_port(self, force_update: bool = False) -> None:
        pass  # no line settings on a virtual board

    def _live(self) -> SimDevice:
        if not self.is_open or self._device is None:
            raise PortNotOpenError()
        return self._device

    @property
    def in_waiting(self) -> int:
        device = self._live()
        try:
            return device.pending(self._generation)
        except DeviceGone as exc:
            raise OSError(errno.EIO, "Input/output error") from exc

    def read(self, size: int = 1) -> bytes:
        device = self._live()
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        data = bytearray()
        while len(data) < size:
            try:
                data += device.read(size - len(data), self._generation)
            except DeviceGone as exc:
                raise SerialException(f"read failed: {exc}") from exc
            now = time.monotonic()
            if len(data) >= size or (deadline is not None and now >= deadline):
                break
            device.wait(now, deadline, MIN_SLEEP_S)
        return bytes(data)

    def write(self, data: bytes) -> int:
        device = self._live()
        try:
            device.write(bytes(data), self._generation)
        except DeviceGone as exc:
            raise SerialException(f"write failed: {exc}") from exc
        return len(data)

    def reset_input_buffer(self) -> None:
        self._live().discard_output()

    def reset_output_buffer(self) -> None:
        self._live()

    @property
    def out_waiting(self) -> int:
        return 0
