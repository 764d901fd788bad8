"""Signed firmware images (PROTOCOL.md § 14.6): the signature trailer, key files and a pure
Ed25519 verifier.

A signed image is ``header ‖ body ‖ trailer``; the header's ``flags`` bit 0 says a trailer
follows. The trailer's Ed25519 signature is over the 96-byte header, which holds the body's
size, CRC-32C and SHA-256, its security counter, version and target: so it covers header and
body, as MCUboot signs an image's hash.

The verifier here is RFC 8032 § 5.1.7 in Python integers (no dependency): the virtual board
verifies with it, and it is checked against RFC 8032's vectors and against the ``cryptography``
package in the tests. It is not constant-time, which verification of public data does not need.
Signing needs the private key and lives on the host (``spiel_edge.device.fwkeys``).
"""

from __future__ import annotations

import hashlib
import re
import struct
from typing import Protocol

__all__ = [
    "DEV_PUBLIC_KEY",
    "SIG_MAGIC",
    "SIG_TRAILER",
    "SIG_TRAILER_SIZE",
    "SIG_TYPE_ED25519",
    "Signer",
    "ed25519_verify",
    "key_id",
    "parse_public_key_text",
    "public_key_text",
]

SIG_MAGIC = b"SPSG"
SIG_TYPE_ED25519 = 1
# magic, sig_type, reserved, sig_len, key_id (first 8 bytes of SHA-256 of the public key), sig
SIG_TRAILER = struct.Struct("<4sBBH8s64s")
SIG_TRAILER_SIZE = SIG_TRAILER.size  # 80

# The development key shipped in firmware_protocol/firmware/keys/ (its private half is public:
# anyone can sign for a board that trusts it). A release build (make RELEASE=1) refuses it.
DEV_PUBLIC_KEY = bytes.fromhex("6bd1f29cbba103ae612f75e650e8b9818673b9ea4a8ce5a1b6dec93dec462b2a")


class Signer(Protocol):
    """What ``pack_image`` signs with: the public key and ``sign(message) -> 64 bytes``."""

    public_key: bytes

    def sign(self, message: bytes) -> bytes: ...


def key_id(public_key: bytes) -> bytes:
    """The 8 bytes a trailer names its key by: a diagnostic, never trusted by itself."""
    return hashlib.sha256(bytes(public_key)).digest()[:8]


# ---- the public key file: what the C build includes (a C initializer list) ------------------

_BYTE = re.compile(r"0x([0-9a-fA-F]{2})")


def public_key_text(public_key: bytes, *, comment: str = "") -> str:
    """The public key file: comment lines and 32 bytes as ``0x..,`` that the C build includes
    inside an array initializer (``SPIEL_FW_KEY``), and this module parses back."""
    if len(public_key) != 32:
        raise ValueError(f"an Ed25519 public key is 32 bytes, got {len(public_key)}")
    lines = [
        f"/* spiel-edge firmware signing public key (Ed25519), key id {key_id(public_key).hex()}"
    ]
    lines += [f" * {line}" for line in comment.splitlines() if line]
    lines.append(" */")
    for row in range(0, 32, 8):
        lines.append(" ".join(f"0x{b:02x}," for b in public_key[row : row + 8]))
    return "\n".join(lines) + "\n"


def parse_public_key_text(text: str) -> bytes:
    """The 32 bytes of a public key file; ValueError if it does not hold exactly 32."""
    body = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    found = bytes(int(h, 16) for h in _BYTE.findall(body))
    if len(found) != 32 or _BYTE.sub("", body).replace(",", "").strip():
        raise ValueError(
            "not a public key file: expected 32 bytes written as 0x.., (keygen's .pub)"
        )
    return found


# ---- Ed25519 verification (RFC 8032 § 5.1) ------------------------------------------------

_P = 2**255 - 19
_L = 2**252 + 27742317777372353535851937790883648493
_D = -121665 * pow(121666, _P - 2, _P) % _P
_SQRT_M1 = pow(2, (_P - 1) // 4, _P)


def _add(a: tuple, b: tuple) -> tuple:
    """Extended twisted Edwards coordinates (X, Y, Z, T), a = -1 (RFC 8032 § 5.1.4)."""
    x1, y1, z1, t1 = a
    x2, y2, z2, t2 = b
    aa = (y1 - x1) * (y2 - x2) % _P
    bb = (y1 + x1) * (y2 + x2) % _P
    cc = 2 * t1 * t2 * _D % _P
    dd = 2 * z1 * z2 % _P
    e, f, g, h = bb - aa, dd - cc, dd + cc, bb + aa
    return (e * f % _P, g * h % _P, f * g % _P, e * h % _P)


def _mul(s: int, p: tuple) -> tuple:
    q = (0, 1, 1, 0)
    while s:
        if s & 1:
            q = _add(q, p)
        p = _add(p, p)
        s >>= 1
    return q


def _encode(p: tuple) -> bytes:
    x, y, z, _ = p
    zi = pow(z, _P - 2, _P)
    x, y = x * zi % _P, y * zi % _P
    return (y | (x & 1) << 255).to_bytes(32, "little")


def _decode(s: bytes) -> tuple | None:
    y = int.from_bytes(s, "little")
    sign, y = y >> 255, y & ((1 << 255) - 1)
    if y >= _P:
        return None
    x2 = (y * y - 1) * pow(_D * y * y + 1, _P - 2, _P) % _P
    x = pow(x2, (_P + 3) // 8, _P)
    if (x * x - x2) % _P:
        x = x * _SQRT_M1 % _P
    if (x * x - x2) % _P or (x == 0 and sign):
        return None
    if x & 1 != sign:
        x = _P - x
    return (x, y, 1, x * y % _P)


_GY = 4 * pow(5, _P - 2, _P) % _P
_G = _decode(_GY.to_bytes(32, "little"))


def ed25519_verify(public_key: bytes, message: bytes, signature: bytes) -> bool:
    """Whether ``signature`` is ``public_key``'s Ed25519 signature of ``message``
    (cofactorless: [S]B = R + [k]A, S < L, as Monocypher and OpenSSL check it)."""
    if len(public_key) != 32 or len(signature) != 64:
        return False
    a = _decode(bytes(public_key))
    r_bytes, s = bytes(signature[:32]), int.from_bytes(signature[32:], "little")
    if a is None or s >= _L or _decode(r_bytes) is None:
        return False
    k = int.from_bytes(
        hashlib.sha512(r_bytes + bytes(public_key) + bytes(message)).digest(), "little"
    )
    minus_a = (_P - a[0], a[1], a[2], _P - a[3])
    return _encode(_add(_mul(s, _G), _mul(k % _L, minus_a))) == r_bytes
