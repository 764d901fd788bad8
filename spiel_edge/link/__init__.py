"""Links: byte pipes to a board, opened by URL through a lazy scheme registry.

    /dev/ttyACM0, serial:///dev/ttyACM0   CDC-ACM serial (pyserial, exclusive open)
    usb://1209:0001[/SERIAL]             USB bulk endpoints on a vendor interface (pyusb)
    sim://[NAME][?query]                 the virtual board (pyserial URL handler, in-process)

A link only moves bytes: ``read(timeout_s) -> bytes`` (b"" when nothing came in time),
``write(data)``, ``close()``. Every failure that means "the board went away" is raised as
DeviceDisconnectedError, so the device session has one thing to catch and reconnect on.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Protocol

from spiel_edge.errors import DeviceError

__all__ = ["LINK_SCHEMES", "Link", "LinkIdentity", "open_link", "scheme_of"]

# scheme -> (module, factory function); imported only when a URL of that scheme is opened.
LINK_SCHEMES: dict[str, tuple[str, str]] = {
    "serial": ("spiel_edge.link.serial_link", "open_serial"),
    "sim": ("spiel_edge.link.serial_link", "open_serial"),
    "usb": ("spiel_edge.link.usb_link", "open_usb"),
}


@dataclass(frozen=True)
class LinkIdentity:
    """What identifies the board behind a link, to find it again after an unplug."""

    url: str
    vid: int | None = None
    pid: int | None = None
    serial: str | None = None


class Link(Protocol):
    url: str

    def read(self, timeout_s: float) -> bytes: ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...

    def identity(self) -> LinkIdentity: ...


def scheme_of(url: str) -> str:
    """The registry scheme of a port URL; a bare path is a serial device."""
    if "://" not in url:
        return "serial"
    return url.split("://", 1)[0].lower()


def open_link(url: str, **options: Any) -> Link:
    """Open ``url``; ``options`` go to the scheme's factory (e.g. ``backend=`` for usb)."""
    scheme = scheme_of(url)
    entry = LINK_SCHEMES.get(scheme)
    if entry is None:
        known = ", ".join(f"{s}://" for s in sorted(LINK_SCHEMES))
        raise DeviceError(
            f"unknown port URL scheme {scheme!r} in {url!r}; known: {known} or a device path"
        )
    module_name, factory_name = entry
    factory = getattr(importlib.import_module(module_name), factory_name)
    return factory(url, **options)
