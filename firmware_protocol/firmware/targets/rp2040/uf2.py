#!/usr/bin/env python3
"""uf2.py OUT.uf2 FILE@ADDRESS...: flat binaries placed at flash addresses (0x10000000 is the
flash's first byte) as one UF2 file for the RP2040's ROM bootloader (BOOTSEL drive): 256 bytes
of payload per 512-byte block, the RP2040 family id; the gaps between files are not written.
Format: github.com/microsoft/uf2."""

import struct
import sys

MAGIC0, MAGIC1, MAGIC_END = 0x0A324655, 0x9E5D5157, 0x0AB16F30
FLAG_FAMILY_ID = 0x00002000
RP2040_FAMILY = 0xE48BFF56
PAYLOAD = 256


def uf2_blocks(parts: list[tuple[int, bytes]]) -> bytes:
    pages: dict[int, bytearray] = {}
    for base, data in parts:
        if base % PAYLOAD:
            raise ValueError(f"0x{base:x} is not 256-byte aligned")
        for off in range(0, len(data), PAYLOAD):
            page = pages.setdefault(base + off, bytearray(b"\xff" * PAYLOAD))
            chunk = data[off : off + PAYLOAD]
            page[: len(chunk)] = chunk
    out = bytearray()
    for i, addr in enumerate(sorted(pages)):
        head = struct.pack(
            "<8I", MAGIC0, MAGIC1, FLAG_FAMILY_ID, addr, PAYLOAD, i, len(pages), RP2040_FAMILY
        )
        out += head + pages[addr] + b"\0" * (476 - PAYLOAD) + struct.pack("<I", MAGIC_END)
    return bytes(out)


def main(argv: list[str]) -> int:
    if len(argv) < 3 or any("@" not in a for a in argv[2:]):
        print(__doc__.splitlines()[0], file=sys.stderr)
        return 2
    parts = []
    for arg in argv[2:]:
        path, addr = arg.rsplit("@", 1)
        with open(path, "rb") as f:
            parts.append((int(addr, 0), f.read()))
    with open(argv[1], "wb") as f:
        f.write(uf2_blocks(parts))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
