"""The virtual board's config flash: two slots, written so that a power cut never loses both.

A commit writes the slot that is not active: erase, data in pages, then the slot header
(magic, generation, length, CRC-32C of the data) last, then reads back and verifies. The
active slot is the valid one with the highest generation, so until the header of the new
slot is written the old config stays active (MCUboot / Zephyr NVS style). ``cut_at`` makes
the N-th flash operation (0-based, counted over the flash's life) fail with PowerCut, leaving
the flash as a real power loss would: earlier operations done, that one not.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from crc32c import crc32c

SLOT_SIZE = 4096
PAGE = 256
HEADER = struct.Struct("<IIII")  # magic, generation, length, crc of the data
MAGIC = 0x53504346  # "FCPS"
ERASED = 0xFF


class PowerCut(Exception):
    """The board lost power during a flash operation."""


class FlashError(Exception):
    """A flash write or its read-back verification failed (``verify`` tells which)."""

    def __init__(self, message: str, verify: bool = False):
        super().__init__(message)
        self.verify = verify


@dataclass(frozen=True)
class SlotInfo:
    slot: int
    valid: bool
    generation: int = 0
    length: int = 0
    crc: int = 0


class Flash:
    def __init__(self, capacity: int = SLOT_SIZE - HEADER.size, cut_at: int = -1):
        self.capacity = capacity
        self.cut_at = cut_at
        self.ops = 0  # flash operations performed (erase, page write, header write)
        self._slots = [bytearray([ERASED]) * (HEADER.size + capacity) for _ in range(2)]

    # --- reading -----------------------------------------------------------------------

    def slot_info(self, slot: int) -> SlotInfo:
        raw = self._slots[slot]
        magic, generation, length, crc = HEADER.unpack_from(raw)
        if magic != MAGIC or length > self.capacity:
            return SlotInfo(slot, False)
        data = bytes(raw[HEADER.size : HEADER.size + length])
        return SlotInfo(slot, crc32c(data) == crc, generation, length, crc)

    def active(self) -> SlotInfo | None:
        valid = [info for info in map(self.slot_info, (0, 1)) if info.valid]
        return max(valid, key=lambda info: info.generation) if valid else None

    def read_active(self) -> bytes | None:
        info = self.active()
        if info is None:
            return None
        start = HEADER.size
        return bytes(self._slots[info.slot][start : start + info.length])

    # --- writing -----------------------------------------------------------------------

    def commit(self, data: bytes) -> SlotInfo:
        """Write ``data`` to the inactive slot and make it active; PowerCut or FlashError."""
        if len(data) > self.capacity:
            raise FlashError(f"{len(data)} bytes exceed the slot capacity {self.capacity}")
        current = self.active()
        target = 0 if current is None else 1 - current.slot
        generation = 1 if current is None else current.generation + 1
        self._erase(target)
        for offset in range(0, len(data), PAGE):
            self._program(target, HEADER.size + offset, data[offset : offset + PAGE])
        crc = crc32c(data)
        self._program(target, 0, HEADER.pack(MAGIC, generation, len(data), crc))
        info = self.slot_info(target)
        if not info.valid or info.generation != generation:
            raise FlashError(
                f"slot {target} read-back does not match what was written", verify=True
            )
        return info

    def _operation(self) -> None:
        if self.ops == self.cut_at:
            self.cut_at = -1  # one cut per request
            raise PowerCut(f"power lost at flash operation {self.ops}")
        self.ops += 1

    def _erase(self, slot: int) -> None:
        self._operation()
        self._slots[slot][:] = bytes([ERASED]) * len(self._slots[slot])

    def _program(self, slot: int, offset: int, data: bytes) -> None:
        self._operation()
        raw = self._slots[slot]
        for i, byte in enumerate(data):  # NOR flash: programming only clears bits
            raw[offset + i] &= byte
