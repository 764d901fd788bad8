#!/usr/bin/env python3
"""uf2.py BIN UF2 [BASE]: a flat binary (objcopy -O binary of an image linked for the flash at
BASE, default 0x10000000) as a UF2 file for the RP2040's ROM bootloader (BOOTSEL drive): 256
bytes of payload per 512-byte block, the RP2040 family id. Format: github.com/microsoft/uf2."""

import struct
import sys

MAGIC0, MAGIC1, MAGIC_END = 0x0A324655, 0x9E5D5157, 0x0AB16F30
FLAG_FAMILY_ID = 0x00002000
RP2040_FAMILY = 0xE48BFF56
PAYLOAD = 256


def uf2_blocks(data: bytes, base: int) -> bytes:
    data += b"\xff" * (-len(data) % PAYLOAD)
    n = len(data) // PAYLOAD
    out = bytearray()
    for i in range(n):
        chunk = data[i * PAYLOAD : (i + 1) * PAYLOAD]
        head = struct.pack(
            "<8I", MAGIC0, MAGIC1, FLAG_FAMILY_ID, base + i * PAYLOAD, PAYLOAD, i, n, RP2040_FAMILY
        )
        out += head + chunk + b"\0" * (476 - PAYLOAD) + struct.pack("<I", MAGIC_END)
    return bytes(out)


def main(argv: list[str]) -> int:
    if len(argv) not in (3, 4):
        print(__doc__.splitlines()[0], file=sys.stderr)
        return 2
    base = int(argv[3], 0) if len(argv) == 4 else 0x10000000
    with open(argv[1], "rb") as f:
        data = f.read()
    if not data:
        print(f"uf2.py: {argv[1]} is empty", file=sys.stderr)
        return 1
    with open(argv[2], "wb") as f:
        f.write(uf2_blocks(data, base))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
