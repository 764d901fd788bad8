"""USB bulk links through pyusb: ``usb://VID:PID[/SERIAL]`` (hexadecimal VID and PID).

The board exposes a vendor-class interface (bInterfaceClass 0xFF) with one bulk IN and one
bulk OUT endpoint carrying the same COBS frames as the serial port. libusb comes from the
system, else from the ``libusb-package`` wheel. Tests pass ``backend=`` a fake
``usb.backend.IBackend`` (:mod:`spiel_edge.sim.usb_backend`) so the real pyusb stack runs.
"""

from __future__ import annotations

import errno
import logging
import re
from typing import Any

import usb.core
import usb.util

from spiel_edge.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError
from spiel_edge.link import LinkIdentity

log = logging.getLogger(__name__)

VENDOR_CLASS = 0xFF
WRITE_TIMEOUT_MS = 1000
READ_PACKETS = 32  # read up to this many max-size packets per call (a multiple, never less)
_URL = re.compile(r"^usb://([0-9a-fA-F]{1,4}):([0-9a-fA-F]{1,4})(?:/([^?]+))?$")
_GONE = {errno.ENODEV, errno.EIO, errno.ENOENT, errno.EPIPE, errno.ESHUTDOWN}


def parse_usb_url(url: str) -> tuple[int, int, str | None]:
    match = _URL.match(url)
    if not match:
        raise DeviceError(
            f"{url!r}: expected usb://VID:PID or usb://VID:PID/SERIAL (hexadecimal ids)"
        )
    vid, pid, serial = match.groups()
    return int(vid, 16), int(pid, 16), serial


def default_backend() -> Any:
    """libusb-1.0 from the system, else the one bundled by the libusb-package wheel."""
    import usb.backend.libusb1

    backend = usb.backend.libusb1.get_backend()
    if backend is None:
        import libusb_package

        backend = libusb_package.get_libusb1_backend()
    if backend is None:
        raise DeviceError("no libusb-1.0 found (install the system libusb or libusb-package)")
    return backend


def serial_of(dev: Any) -> str | None:
    try:
        return dev.serial_number
    except (usb.core.USBError, ValueError, NotImplementedError):  # no permission or no strings
        return None


def find_usb_devices(
    vid: int, pid: int, serial: str | None = None, backend: Any = None
) -> list[Any]:
    backend = backend if backend is not None else default_backend()
    found = usb.core.find(find_all=True, idVendor=vid, idProduct=pid, backend=backend)
    return [d for d in found if serial is None or serial_of(d) == serial]


class UsbLink:
    """Bulk IN/OUT endpoints of a claimed vendor interface as a Link."""

    def __init__(self, url: str, dev: Any, interface: int, ep_in: Any, ep_out: Any):
        self.url = url
        self._dev, self._interface = dev, interface
        self._ep_in, self._ep_out = ep_in, ep_out
        self._read_size = ep_in.wMaxPacketSize * READ_PACKETS
        self._identity = LinkIdentity(url, dev.idVendor, dev.idProduct, serial_of(dev))

    def read(self, timeout_s: float) -> bytes:
        try:
            data = self._dev.read(
                self._ep_in.bEndpointAddress, self._read_size, max(1, round(timeout_s * 1000))
            )
        except usb.core.USBTimeoutError:
            return b""
        except usb.core.USBError as exc:
            raise _usb_error(self.url, exc) from exc
        return bytes(data)

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        try:
            while view:
                sent = self._dev.write(self._ep_out.bEndpointAddress, view, WRITE_TIMEOUT_MS)
                view = view[sent:]
        except usb.core.USBTimeoutError as exc:
            raise DeviceTimeoutError(f"{self.url}: the board stopped taking data") from exc
        except usb.core.USBError as exc:
            raise _usb_error(self.url, exc) from exc

    def close(self) -> None:
        try:
            usb.util.release_interface(self._dev, self._interface)
        except (usb.core.USBError, NotImplementedError) as exc:
            log.debug("%s: release: %s", self.url, exc)
        usb.util.dispose_resources(self._dev)

    def identity(self) -> LinkIdentity:
        return self._identity


def _usb_error(url: str, exc: usb.core.USBError) -> DeviceError:
    if exc.errno in _GONE:
        return DeviceDisconnectedError(f"{url}: link lost: {exc}")
    if exc.errno == errno.EACCES:
        return DeviceError(f"{url}: permission denied; install the udev rule from the README")
    return DeviceError(f"{url}: USB error: {exc}")


def _vendor_interface(dev: Any) -> tuple[Any, Any, Any]:
    cfg = dev.get_active_configuration()
    for intf in cfg:
        if intf.bInterfaceClass != VENDOR_CLASS:
            continue
        ep_in = usb.util.find_descriptor(
            intf, custom_match=lambda e: _bulk(e, usb.util.ENDPOINT_IN)
        )
        ep_out = usb.util.find_descriptor(
            intf, custom_match=lambda e: _bulk(e, usb.util.ENDPOINT_OUT)
        )
        if ep_in is not None and ep_out is not None:
            return intf, ep_in, ep_out
    raise DeviceError("the USB device has no vendor interface with bulk IN and OUT endpoints")


def _bulk(ep: Any, direction: int) -> bool:
    return (
        usb.util.endpoint_type(ep.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
        and usb.util.endpoint_direction(ep.bEndpointAddress) == direction
    )


def open_usb(url: str, *, backend: Any = None, exclusive: bool = True) -> UsbLink:
    """Find, configure and claim the board; absent -> DeviceDisconnectedError."""
    del exclusive  # claiming the interface is exclusive already
    vid, pid, serial = parse_usb_url(url)
    devices = find_usb_devices(vid, pid, serial, backend)
    if not devices:
        raise DeviceDisconnectedError(f"{url}: no such USB device")
    dev = devices[0]
    try:
        try:
            dev.get_active_configuration()
        except usb.core.USBError:
            dev.set_configuration()
        intf, ep_in, ep_out = _vendor_interface(dev)
        number = intf.bInterfaceNumber
        try:
            if dev.is_kernel_driver_active(number):
                dev.detach_kernel_driver(number)
        except (NotImplementedError, usb.core.USBError):
            pass  # not every backend or OS has kernel drivers to detach
        usb.util.claim_interface(dev, number)
    except usb.core.USBError as exc:
        raise _usb_error(url, exc) from exc
    return UsbLink(url, dev, number, ep_in, ep_out)
