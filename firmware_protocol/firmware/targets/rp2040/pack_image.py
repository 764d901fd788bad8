#!/usr/bin/env python3
"""pack_image.py BODY VERSION TARGET OUT [KEY.key KEY.pub [COUNTER]]: a firmware image (the
96-byte header of PROTOCOL.md 14.3 + BODY, + the Ed25519 signature trailer of 14.6 when a key is
given), as `spiel-edge firmware pack --key` writes it, for the build (which must not need the
spiel-edge package): the image a new board's slot 0 holds in firmware.uf2. The header layout
is spiel_edge/protocol/image.py's; tests/firmware/test_rp2040.py checks both agree.
Signing (a PKCS#8 PEM Ed25519 key, as `spiel-edge firmware keygen` writes it) uses the
`cryptography` package when it is there, else `openssl pkeyutl` (OpenSSL 3); KEY.pub (the
public key the build includes) must be its public half."""

import hashlib
import re
import struct
import subprocess
import sys
import tempfile

HEADER = struct.Struct("<4sHH16s16sBBHII32s8sI")


def crc32c(data: bytes) -> int:
    table = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    crc = 0xFFFFFFFF
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def pack(body: bytes, version: str, target: str, signed: bool = False, counter: int = 0) -> bytes:
    head = HEADER.pack(
        b"SPFW",
        1,
        HEADER.size,
        version.encode(),
        target.encode(),
        1,
        2,
        int(signed),
        len(body),
        crc32c(body),
        hashlib.sha256(body).digest(),
        struct.pack("<I", counter) + bytes(4),
        0,
    )
    return head[:-4] + struct.pack("<I", crc32c(head[:-4])) + body


def sign(private: str, message: bytes) -> tuple[bytes, bytes]:
    """(public key, Ed25519 signature of message) by the PEM private key file."""
    try:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    except ImportError:
        return sign_openssl(private, message)
    with open(private, "rb") as f:
        key = serialization.load_pem_private_key(f.read(), password=None)
    if not isinstance(key, Ed25519PrivateKey):
        raise SystemExit(f"pack_image.py: {private}: not an Ed25519 private key")
    raw = key.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return raw, key.sign(message)


def sign_openssl(private: str, message: bytes) -> tuple[bytes, bytes]:
    with tempfile.NamedTemporaryFile() as msg:
        msg.write(message)
        msg.flush()
        try:
            sig = subprocess.run(
                ["openssl", "pkeyutl", "-sign", "-rawin", "-inkey", private, "-in", msg.name],
                capture_output=True,
                check=True,
            ).stdout
            der = subprocess.run(
                ["openssl", "pkey", "-in", private, "-pubout", "-outform", "DER"],
                capture_output=True,
                check=True,
            ).stdout
        except (OSError, subprocess.CalledProcessError) as exc:
            raise SystemExit(
                f"pack_image.py: signing needs the Python package cryptography or OpenSSL 3 ({exc})"
            ) from exc
    return der[-32:], sig


def public_key(path: str) -> bytes:
    with open(path) as f:
        text = re.sub(r"/\*.*?\*/", "", f.read(), flags=re.S)
    return bytes(int(h, 16) for h in re.findall(r"0x([0-9a-fA-F]{2})", text))


def main(argv: list[str]) -> int:
    if len(argv) not in (5, 7, 8):
        print(__doc__.splitlines()[0], file=sys.stderr)
        return 2
    with open(argv[1], "rb") as f:
        body = f.read()
    if len(argv) == 5:
        image = pack(body, argv[2], argv[3])
    else:
        image = pack(body, argv[2], argv[3], True, int(argv[7]) if len(argv) == 8 else 0)
        public, signature = sign(argv[5], image[: HEADER.size])
        if public != public_key(argv[6]):
            raise SystemExit(
                f"pack_image.py: {argv[5]} is not the private half of {argv[6]} (FW_KEY): "
                "set FW_SIGN_KEY to the key that pairs with FW_KEY"
            )
        kid = hashlib.sha256(public).digest()[:8]
        image += struct.pack("<4sBBH8s64s", b"SPSG", 1, 0, 64, kid, signature)
    with open(argv[4], "wb") as f:
        f.write(image)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
