"""Finding boards by USB vendor/product id: at start (no --port) and after an unplug."""

from __future__ import annotations

import logging
from typing import Any

import serial.tools.list_ports

from spiel_edge.errors import DeviceError
from spiel_edge.link import LinkIdentity
from spiel_edge.link.usb_ids import board_usb_ids

log = logging.getLogger(__name__)

# the ids live in link/usb_ids.py (one line, or $SPIEL_USB_IDS); read once at import
BOARD_USB_IDS: tuple[tuple[int, int], ...] = board_usb_ids()


def _is_board(vid: int | None, pid: int | None, ids: tuple[tuple[int, int], ...]) -> bool:
    return vid is not None and (vid, pid) in ids


def find_serial_boards(ids: tuple[tuple[int, int], ...] = BOARD_USB_IDS) -> list[LinkIdentity]:
    return [
        LinkIdentity(info.device, info.vid, info.pid, info.serial_number)
        for info in sorted(serial.tools.list_ports.comports(), key=lambda i: i.device)
        if _is_board(info.vid, info.pid, ids)
    ]


def find_usb_boards(
    ids: tuple[tuple[int, int], ...] = BOARD_USB_IDS, backend: Any = None
) -> list[LinkIdentity]:
    """Boards reachable over bulk endpoints; empty when no libusb is available."""
    from spiel_edge.link.usb_link import find_usb_devices, serial_of

    found = []
    for vid, pid in ids:
        try:
            devices = find_usb_devices(vid, pid, None, backend)
        except (DeviceError, OSError, ValueError) as exc:  # no libusb, no permission
            log.debug("USB enumeration unavailable: %s", exc)
            return found
        for dev in devices:
            serial_number = serial_of(dev)
            suffix = f"/{serial_number}" if serial_number else ""
            found.append(
                LinkIdentity(f"usb://{vid:04x}:{pid:04x}{suffix}", vid, pid, serial_number)
            )
    return found


def find_boards(
    ids: tuple[tuple[int, int], ...] = BOARD_USB_IDS, usb_backend: Any = None
) -> list[LinkIdentity]:
    """Every attached board: serial ports first, then bulk-only boards not already listed."""
    boards = find_serial_boards(ids)
    serials = {b.serial for b in boards if b.serial}
    boards += [
        b for b in find_usb_boards(ids, usb_backend) if not b.serial or b.serial not in serials
    ]
    return boards


def default_port(ids: tuple[tuple[int, int], ...] = BOARD_USB_IDS, usb_backend: Any = None) -> str:
    """The URL of the one attached board, or DeviceError saying how to name one."""
    boards = find_boards(ids, usb_backend)
    if len(boards) == 1:
        log.info("found board %s", boards[0].url)
        return boards[0].url
    wanted = ", ".join(f"{v:04x}:{p:04x}" for v, p in ids)
    if not boards:
        raise DeviceError(
            f"no board found (looked for USB ids {wanted}); name one with --port /dev/ttyACM0, "
            "--port usb://VID:PID[/SERIAL] or SPIEL_PORT, or run the virtual board: --port sim://"
        )
    listed = ", ".join(b.url for b in boards)
    raise DeviceError(f"several boards found ({listed}); choose one with --port")


def find_again(identity: LinkIdentity) -> str | None:
    """The current serial URL of a board known by VID/PID/serial (its ttyACM number may
    change when it comes back), or None."""
    if identity.vid is None:
        return None
    for info in serial.tools.list_ports.comports():
        same = (info.vid, info.pid) == (identity.vid, identity.pid)
        if same and (identity.serial is None or info.serial_number == identity.serial):
            return info.device
    return None
