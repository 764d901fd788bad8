"""Signed test images: the development key (firmware_protocol/firmware/keys/dev.key), which
every board built from this tree trusts unless built with another FW_KEY."""

from __future__ import annotations

import functools
from pathlib import Path

from spiel_edge.protocol.image import pack_image

ROOT = Path(__file__).resolve().parents[1]
DEV_KEY = ROOT / "firmware_protocol" / "firmware" / "keys" / "dev.key"
DEV_PUB = ROOT / "firmware_protocol" / "firmware" / "keys" / "dev.pub"


@functools.cache
def dev_signer():
    from spiel_edge.device.fwkeys import load_private_key

    return load_private_key(DEV_KEY)


def signed_image(body: bytes, **kwargs) -> bytes:
    """``pack_image`` signed with the development key (``signer=`` overrides it)."""
    kwargs.setdefault("signer", dev_signer())
    return pack_image(body, **kwargs)
