"""Firmware images: a 96-byte header (magic, version, target, protocol range, size, hashes,
security counter), the body and, when signed, an 80-byte signature trailer. Pure: ``pack_image``
builds one (signing it with a ``Signer``), ``parse_image`` checks one (PROTOCOL.md § 14.3),
``verify_image`` checks its signature and counter (§ 14.6), ``check_body`` checks that a body
can run on a target whose boot stage jumps into a flat binary (mps2-an386).

The header carries the body's size, CRC-32C and SHA-256 and its own CRC-32C, so a host checks
an image file before it sends a byte, and a device checks the slot again before it boots it.
The signature is over the header, so it covers the body through the header's SHA-256.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass

from crc32c import crc32c

from spiel_edge.protocol.errors import ErrorCode, ProtocolError
from spiel_edge.protocol.signing import (
    SIG_MAGIC,
    SIG_TRAILER,
    SIG_TRAILER_SIZE,
    SIG_TYPE_ED25519,
    Signer,
    ed25519_verify,
    key_id,
)

__all__ = [
    "IMAGE_HEADER",
    "IMAGE_HEADER_FIELDS",
    "IMAGE_HEADER_SIZE",
    "IMAGE_MAGIC",
    "ImageError",
    "ImageHeader",
    "ImageRefused",
    "check_body",
    "pack_image",
    "parse_image",
    "verify_image",
]

IMAGE_MAGIC = b"SPFW"
IMAGE_HEADER_VERSION = 1
FLAG_SIGNED = 0x0001  # an 80-byte signature trailer follows the body
# (name, struct code, meaning); header_crc covers every byte before it
IMAGE_HEADER_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("magic", "4s", "the bytes SPFW"),
    ("header_version", "H", "image header layout version = 1"),
    ("header_size", "H", "offset of the body = 96"),
    ("version", "16s", "firmware version text, NUL-padded"),
    ("target", "16s", "board target the image runs on, NUL-padded"),
    ("min_protocol", "B", "lowest protocol version the firmware speaks"),
    ("max_protocol", "B", "highest protocol version the firmware speaks"),
    ("flags", "H", "bit 0: signed (a signature trailer follows the body); others 0"),
    ("body_size", "I", "bytes of the body after the header"),
    ("body_crc", "I", "CRC-32C of the body"),
    ("body_sha256", "32s", "SHA-256 of the body"),
    ("security_counter", "I", "anti-rollback: a board refuses an image below its counter"),
    ("reserved", "4s", "zeros"),
    ("header_crc", "I", "CRC-32C of the header bytes before this field"),
)
IMAGE_HEADER = struct.Struct("<" + "".join(code for _, code, _ in IMAGE_HEADER_FIELDS))
IMAGE_HEADER_SIZE = IMAGE_HEADER.size  # 96


class ImageError(ProtocolError):
    """A firmware image that must not be sent or booted."""


class ImageRefused(ImageError):
    """An intact image a board would refuse for its signature or counter; ``code`` is the
    ErrorCode the board answers FW_VERIFY with."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class ImageHeader:
    version: str
    target: str
    min_protocol: int
    max_protocol: int
    body_size: int
    body_crc: int
    body_sha256: bytes
    security_counter: int = 0
    signed: bool = False
    key_id: bytes = b""  # the trailer's key id (8 bytes), when signed

    @property
    def image_size(self) -> int:
        return IMAGE_HEADER_SIZE + self.body_size + (SIG_TRAILER_SIZE if self.signed else 0)

    def speaks(self, low: int, high: int) -> bool:
        """Whether the firmware shares a protocol version with the range ``low..high``."""
        return self.min_protocol <= high and low <= self.max_protocol


def _text(value: str, name: str) -> bytes:
    raw = value.encode("utf-8")
    if not raw or len(raw) > 16 or b"\x00" in raw:
        raise ImageError(f"{name} must be 1 to 16 bytes of UTF-8 without NUL, got {value!r}")
    return raw


def pack_image(
    body: bytes,
    *,
    version: str,
    target: str,
    min_protocol: int = 1,
    max_protocol: int = 2,
    security_counter: int = 0,
    signer: Signer | None = None,
) -> bytes:
    """Header + body of a firmware image, + the signature trailer when ``signer`` is given."""
    if not 1 <= min_protocol <= max_protocol <= 255:
        raise ImageError(f"protocol range {min_protocol}-{max_protocol} is not valid")
    if not 0 <= security_counter <= 0xFFFF_FFFF:
        raise ImageError(f"security counter {security_counter} is not a u32")
    body = bytes(body)
    head = IMAGE_HEADER.pack(
        IMAGE_MAGIC,
        IMAGE_HEADER_VERSION,
        IMAGE_HEADER_SIZE,
        _text(version, "version"),
        _text(target, "target"),
        min_protocol,
        max_protocol,
        FLAG_SIGNED if signer is not None else 0,
        len(body),
        crc32c(body),
        hashlib.sha256(body).digest(),
        security_counter,
        bytes(4),
        0,
    )
    head = head[:-4] + crc32c(head[:-4]).to_bytes(4, "little")
    if signer is None:
        return head + body
    public = bytes(signer.public_key)
    signature = bytes(signer.sign(head))
    if len(public) != 32 or len(signature) != 64:
        raise ImageError("the signer did not give an Ed25519 key and signature")
    trailer = SIG_TRAILER.pack(SIG_MAGIC, SIG_TYPE_ED25519, 0, 64, key_id(public), signature)
    return head + body + trailer


# Targets whose body is a flat binary the boot stage jumps into: (run address, RAM start, RAM
# end) of its vector table's reset handler and initial stack pointer (targets/*/mps2.h).
FLAT_TARGETS: dict[str, tuple[int, int, int]] = {
    "mps2-an386": (0x0001_0000, 0x2000_0000, 0x2020_0000),
    "rp2040": (0x1001_1000, 0x2000_0000, 0x2004_2000),  # targets/rp2040/rp2040_board.h
}


def check_body(body: bytes, target: str) -> None:
    """ImageError when ``body`` cannot run on ``target``'s boot stage (a flat binary linked for
    its execution region, starting with a vector table); other targets are not checked."""
    if target not in FLAT_TARGETS:
        return
    base, ram_lo, ram_hi = FLAT_TARGETS[target]
    if body[:4] == b"\x7fELF":
        raise ImageError(
            f"{target} takes the flat binary (app.bin, which make TARGET=mps2 writes), not an ELF"
        )
    if len(body) < 8:
        raise ImageError(
            f"a {target} body starts with a vector table: {len(body)} bytes is too short"
        )
    sp, pc = struct.unpack_from("<II", body)
    if not (ram_lo < sp <= ram_hi and pc & 1 and base < pc < base + len(body)):
        raise ImageError(
            f"not a {target} application: initial SP {sp:#x}, reset handler {pc:#x} "
            f"(expected a stack in {ram_lo:#x}-{ram_hi:#x} and code linked at {base:#x})"
        )


def parse_image(image: bytes) -> ImageHeader:
    """The header of a complete, intact image; ImageError saying what is wrong otherwise."""
    image = bytes(image)
    if len(image) < IMAGE_HEADER_SIZE:
        raise ImageError(f"{len(image)} bytes is shorter than the {IMAGE_HEADER_SIZE}-byte header")
    fields = IMAGE_HEADER.unpack_from(image)
    magic, hver, hsize, version, target, lo, hi, flags, size, crc, sha, counter, _, hcrc = fields
    if magic != IMAGE_MAGIC:
        raise ImageError(f"not a spiel-edge firmware image (magic {magic!r}, expected b'SPFW')")
    if crc32c(image[: IMAGE_HEADER_SIZE - 4]) != hcrc:
        raise ImageError("the image header is corrupt (header CRC mismatch)")
    if hver != IMAGE_HEADER_VERSION or hsize != IMAGE_HEADER_SIZE:
        raise ImageError(f"image header version {hver} size {hsize} is not supported")
    if not 1 <= lo <= hi:
        raise ImageError(f"the image declares an empty protocol range {lo}-{hi}")
    signed = bool(flags & FLAG_SIGNED)
    body, trailer = (
        image[IMAGE_HEADER_SIZE : IMAGE_HEADER_SIZE + size],
        image[IMAGE_HEADER_SIZE + size :],
    )
    if len(body) < size:
        raise ImageError(
            f"the image is truncated: its header says {size} body bytes, {len(body)} are there"
        )
    if signed and len(trailer) < SIG_TRAILER_SIZE:
        raise ImageRefused(
            ErrorCode.FW_BAD_SIGNATURE,
            f"the image's signature is truncated ({len(trailer)} of {SIG_TRAILER_SIZE} trailer bytes)",
        )
    extra = len(trailer) - (SIG_TRAILER_SIZE if signed else 0)
    if extra > 0:
        raise ImageError(f"the image has {extra} bytes after its declared end")
    if crc32c(body) != crc:
        raise ImageError("the image body is corrupt (CRC-32C mismatch)")
    if hashlib.sha256(body).digest() != sha:
        raise ImageError("the image body is corrupt (SHA-256 mismatch)")
    return ImageHeader(
        version.rstrip(b"\x00").decode("utf-8", "replace"),
        target.rstrip(b"\x00").decode("utf-8", "replace"),
        lo,
        hi,
        size,
        crc,
        sha,
        counter,
        signed,
        SIG_TRAILER.unpack(trailer)[4] if signed else b"",
    )


def verify_image(image: bytes, public_key: bytes, min_counter: int = 0) -> ImageHeader:
    """The header of an intact image signed by ``public_key`` whose security counter is at
    least ``min_counter``; ImageRefused (with the board's error code) or ImageError otherwise.
    The checks and their order are the boards' (PROTOCOL.md § 14.6)."""
    header = parse_image(image)
    if not header.signed:
        raise ImageRefused(ErrorCode.FW_UNSIGNED, "the image is not signed (pack it with --key)")
    magic, sig_type, _, sig_len, kid, signature = SIG_TRAILER.unpack_from(
        image, header.image_size - SIG_TRAILER_SIZE
    )
    if magic != SIG_MAGIC or sig_type != SIG_TYPE_ED25519 or sig_len != 64:
        raise ImageRefused(ErrorCode.FW_BAD_SIGNATURE, "the image's signature trailer is damaged")
    if kid != key_id(public_key):
        raise ImageRefused(
            ErrorCode.FW_WRONG_KEY,
            f"the image is signed by key {kid.hex()}, the board trusts {key_id(public_key).hex()}",
        )
    if not ed25519_verify(public_key, image[:IMAGE_HEADER_SIZE], signature):
        raise ImageRefused(
            ErrorCode.FW_BAD_SIGNATURE,
            "the image's signature does not verify (header or body changed after signing)",
        )
    if header.security_counter < min_counter:
        raise ImageRefused(
            ErrorCode.FW_ROLLBACK,
            f"the image's security counter {header.security_counter} is below the board's "
            f"{min_counter} (a downgrade)",
        )
    return header
