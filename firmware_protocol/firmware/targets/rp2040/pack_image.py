#!/usr/bin/env python3
"""pack_image.py BODY VERSION TARGET OUT: a firmware image (the 96-byte header of PROTOCOL.md
14.3 + BODY), as `spiel-edge firmware pack` writes it, for the build (which must not need the
spiel-edge package): the image a new board's slot 0 holds in firmware.uf2. The header layout
is firmware_protocol/image.py's; tests/firmware/test_rp2040.py checks both agree."""

import hashlib
import struct
import sys

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


def pack(body: bytes, version: str, target: str) -> bytes:
    head = HEADER.pack(
        b"SPFW",
        1,
        HEADER.size,
        version.encode(),
        target.encode(),
        1,
        2,
        0,
        len(body),
        crc32c(body),
        hashlib.sha256(body).digest(),
        bytes(8),
        0,
    )
    return head[:-4] + struct.pack("<I", crc32c(head[:-4])) + body


def main(argv: list[str]) -> int:
    if len(argv) != 5:
        print(__doc__.splitlines()[0], file=sys.stderr)
        return 2
    with open(argv[1], "rb") as f:
        body = f.read()
    with open(argv[4], "wb") as f:
        f.write(pack(body, argv[2], argv[3]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
