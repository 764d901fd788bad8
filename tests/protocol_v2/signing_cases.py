"""Forged, tampered, unsigned and downgraded images, made the way an attacker would (header
CRC and body digests recomputed so only the signature can tell), and a raw upload that goes
past the host's own checks, shared by the virtual board's, the posix and the qemu tests."""

from __future__ import annotations

import hashlib
from pathlib import Path

from crc32c import crc32c

from spiel_edge.device import DeviceSession
from spiel_edge.device.firmware import verify_upload
from spiel_edge.errors import DeviceRequestError
from spiel_edge.protocol.image import (
    IMAGE_HEADER,
    IMAGE_HEADER_FIELDS,
    IMAGE_HEADER_SIZE,
    pack_image,
)
from spiel_edge.protocol.link_messages import FwBegin, FwWrite
from tests.fwsign import signed_image

NAMES = [name for name, _, _ in IMAGE_HEADER_FIELDS]


def reheader(image: bytes, body: bytes | None = None, **changes) -> bytes:
    """``image`` with header fields changed (and the body replaced, its size, CRC-32C and
    SHA-256 put in the header), the header CRC recomputed, the trailer kept as it was."""
    values = dict(zip(NAMES, IMAGE_HEADER.unpack_from(image), strict=True))
    old_size = values["body_size"]
    trailer = image[IMAGE_HEADER_SIZE + old_size :]
    if body is None:
        body = image[IMAGE_HEADER_SIZE : IMAGE_HEADER_SIZE + old_size]
    else:
        values.update(
            body_size=len(body), body_crc=crc32c(body), body_sha256=hashlib.sha256(body).digest()
        )
    values.update(changes)
    head = IMAGE_HEADER.pack(*(values[n] for n in NAMES))[:-4]
    return head + crc32c(head).to_bytes(4, "little") + body + trailer


def forged_images(good: bytes, other_signer) -> dict[str, tuple[bytes, str]]:
    """name -> (image, the ErrorCode name a board answers FW_VERIFY with)."""
    values = dict(zip(NAMES, IMAGE_HEADER.unpack_from(good), strict=True))
    body = good[IMAGE_HEADER_SIZE : IMAGE_HEADER_SIZE + values["body_size"]]
    kwargs = {
        "version": values["version"].rstrip(b"\0").decode(),
        "target": values["target"].rstrip(b"\0").decode(),
        "security_counter": values["security_counter"],
    }
    evil = bytearray(body)
    evil[len(evil) // 2] ^= 0x20  # a byte of the body rewritten (its serial, say)
    return {
        "tampered header": (reheader(good, version=b"9.9.9".ljust(16, b"\0")), "FW_BAD_SIGNATURE"),
        "tampered counter": (reheader(good, security_counter=1 << 20), "FW_BAD_SIGNATURE"),
        "tampered body": (reheader(good, bytes(evil)), "FW_BAD_SIGNATURE"),
        "wrong key": (signed_image(body, signer=other_signer, **kwargs), "FW_WRONG_KEY"),
        "truncated signature": (good[:-40], "FW_BAD_SIGNATURE"),
        "unsigned": (pack_image(body, **kwargs), "FW_UNSIGNED"),
    }


def other_signer(tmp_path: Path):
    from spiel_edge.device.fwkeys import generate_key

    return generate_key(tmp_path / "other.key", tmp_path / "other.pub")


def raw_upload(port: str, image: bytes) -> str | None:
    """FW_BEGIN, FW_WRITE, FW_VERIFY (asynchronous, as the host asks it) with no host check:
    None if the board accepted it, else the name of the error code it answered."""
    with DeviceSession(port, reconnect=False) as dev:
        try:
            dev.request(FwBegin(len(image), crc32c(image), hashlib.sha256(image).digest()))
            step = min(dev.max_payload, 1024) - 6
            for off in range(0, len(image), step):
                dev.request(FwWrite(off, image[off : off + step]))
            verify_upload(dev)
        except DeviceRequestError as exc:
            from spiel_edge.protocol import ErrorCode

            return ErrorCode(exc.code).name
    return None
