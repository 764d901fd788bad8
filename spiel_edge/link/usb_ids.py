"""The board's USB vendor/product ids: the one place discovery, the udev rule, doctor and the
virtual board read them from.

A product with its own ids changes BOARD_USB_IDS below (one line), or, without touching the
code, sets ``SPIEL_USB_IDS=VID:PID[,VID:PID...]`` (hexadecimal) in the environment, e.g. in
/etc/spiel-edge/spiel-edge.env, before `spiel-edge service install` renders the udev rule.
How to obtain ids of your own (pid.codes, USB-IF): docs/aarch64.md, "A USB id that is ours".
"""

from __future__ import annotations

import os

from spiel_edge.errors import ConfigError

# 1209:0001 is pid.codes' shared *test* id: fine on a bench, not for a product (other boards
# carry it too, so discovery and the udev rule may claim them). Replace with the product's ids.
BOARD_USB_IDS: tuple[tuple[int, int], ...] = ((0x1209, 0x0001),)

ENV_VAR = "SPIEL_USB_IDS"


def parse_usb_ids(text: str) -> tuple[tuple[int, int], ...]:
    """``"1209:0001,1209:abcd"`` -> ((0x1209, 0x0001), (0x1209, 0xabcd)); ConfigError if bad."""
    ids = []
    for item in filter(None, (part.strip() for part in text.split(","))):
        vid, sep, pid = item.partition(":")
        try:
            pair = (int(vid, 16), int(pid, 16))
        except ValueError:
            pair = (-1, -1)
        if not sep or not all(0 <= v <= 0xFFFF for v in pair):
            raise ConfigError(f"{ENV_VAR}={text!r}: expected VID:PID[,VID:PID...] in hexadecimal")
        ids.append(pair)
    if not ids:
        raise ConfigError(f"{ENV_VAR}={text!r}: no VID:PID given")
    return tuple(ids)


def board_usb_ids(environ: dict[str, str] | None = None) -> tuple[tuple[int, int], ...]:
    """``$SPIEL_USB_IDS`` when set, else BOARD_USB_IDS."""
    text = (os.environ if environ is None else environ).get(ENV_VAR, "").strip()
    return parse_usb_ids(text) if text else BOARD_USB_IDS
