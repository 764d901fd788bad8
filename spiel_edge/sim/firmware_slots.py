"""The virtual board's firmware flash: two image slots, a boot record and the boot choice.

What MCUboot's test/confirm does, modelled on the operations a power cut can interrupt: an
upload erases the inactive slot and writes it chunk by chunk; FW_TEST writes a boot record
"test slot S once"; at boot the bootloader turns a pending test into a trial (record first,
then the jump), and a trial still unconfirmed at the next boot into a rollback. The boot
record is kept twice (generation + CRC, like the config slots) so a cut while writing it
leaves the previous one. Whatever slot the record names is booted only if its image passes
``parse_image`` (length, CRC-32C, SHA-256); else the other slot, else nothing (the board then
stays in its recovery loader and answers only HELLO and FW_* requests).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from crc32c import crc32c

from firmware_protocol.image import ImageError, ImageHeader, pack_image, parse_image
from firmware_protocol.v2_messages import BootState, SlotState
from spiel_edge.sim.flash import PowerCut

SLOT_SIZE = 64 * 1024
RECORD = struct.Struct("<IIBBBBI")  # magic, generation, confirmed, trial, state, 0, crc
RECORD_MAGIC = 0x42545053  # "SPTB"
NO_SLOT = 0xFF
TARGET = "sim"
FACTORY_VERSION = "sim-0.1.0"
SILENT_MARK = b"SIM:SILENT"  # an image body starting with this boots but never answers


def factory_image(max_protocol: int = 2) -> bytes:
    return pack_image(
        b"SIM:OK factory firmware of the virtual board",
        version=FACTORY_VERSION,
        target=TARGET,
        min_protocol=1,
        max_protocol=max_protocol,
    )


@dataclass(frozen=True)
class BootRecord:
    confirmed: int = 0
    trial: int = NO_SLOT
    state: int = BootState.CONFIRMED  # CONFIRMED, TEST_PENDING or TRIAL


class FirmwareFlash:
    """Two slots and two boot record copies; ``cut_at`` cuts power at that flash operation."""

    def __init__(self, *, cut_at: int = -1, factory: bytes | None = None):
        self.slot_size = SLOT_SIZE
        self.cut_at = cut_at
        self.ops = 0
        self.slots = [bytearray(b"\xff") * SLOT_SIZE for _ in range(2)]
        self.lengths = [0, 0]  # bytes written contiguously from 0 (what the slot holds)
        self._records = [bytearray(b"\xff") * RECORD.size for _ in range(2)]
        image = factory if factory is not None else factory_image()
        self.slots[0][: len(image)] = image
        self.lengths[0] = len(image)
        self.running = 0
        self.boot_state = BootState.CONFIRMED

    # --- flash operations (each may be cut) ----------------------------------------------

    def _op(self) -> None:
        if self.ops == self.cut_at:
            self.cut_at = -1
            raise PowerCut(f"power lost at firmware flash operation {self.ops}")
        self.ops += 1

    def erase(self, slot: int) -> None:
        self._op()
        self.slots[slot][:] = b"\xff" * self.slot_size
        self.lengths[slot] = 0

    def program(self, slot: int, offset: int, data: bytes) -> None:
        self._op()
        self.slots[slot][offset : offset + len(data)] = data
        self.lengths[slot] = max(self.lengths[slot], offset + len(data))

    def write_record(self, record: BootRecord) -> None:
        current = self._newest()
        generation = 1 if current is None else current[0] + 1
        copy = generation % 2
        body = RECORD.pack(
            RECORD_MAGIC, generation, record.confirmed, record.trial, record.state, 0, 0
        )[:-4]
        self._op()  # erase + program of one small sector, one operation
        self._records[copy][:] = body + crc32c(body).to_bytes(4, "little")

    # --- reading ---------------------------------------------------------------------------

    def _newest(self) -> tuple[int, BootRecord] | None:
        best = None
        for raw in self._records:
            magic, gen, confirmed, trial, state, _, crc = RECORD.unpack(raw)
            if magic != RECORD_MAGIC or crc32c(bytes(raw[:-4])) != crc:
                continue
            if best is None or gen > best[0]:
                best = (gen, BootRecord(confirmed, trial, state))
        return best

    def record(self) -> BootRecord:
        newest = self._newest()
        return BootRecord() if newest is None else newest[1]

    def image(self, slot: int) -> bytes:
        return bytes(self.slots[slot][: self.lengths[slot]])

    def header(self, slot: int) -> ImageHeader | None:
        try:
            return parse_image(self.image(slot))
        except ImageError:
            return None

    def slot_state(self, slot: int) -> int:
        if self.lengths[slot] == 0:
            return SlotState.EMPTY
        return SlotState.PARTIAL if self.header(slot) is None else SlotState.VERIFIED

    # --- the bootloader --------------------------------------------------------------------

    def boot(self) -> int | None:
        """Choose and record the slot to run, as the bootloader does at reset; None: no
        bootable image (recovery loader). PowerCut may propagate (the next boot retries)."""
        rec = self.record()
        choice, state = rec.confirmed, BootState.CONFIRMED
        if rec.state == BootState.TEST_PENDING and rec.trial != NO_SLOT:
            if self.header(rec.trial) is not None:
                self.write_record(BootRecord(rec.confirmed, rec.trial, BootState.TRIAL))
                choice, state = rec.trial, BootState.TRIAL
            else:
                self.write_record(BootRecord(rec.confirmed))
        elif rec.state == BootState.TRIAL:  # reset before confirm: roll back
            self.write_record(BootRecord(rec.confirmed))
        if self.header(choice) is None:
            other = 1 - choice
            if self.header(other) is None:
                self.running, self.boot_state = NO_SLOT, BootState.CONFIRMED
                return None
            self.write_record(BootRecord(other))
            choice, state = other, BootState.CONFIRMED
        self.running, self.boot_state = choice, state
        return choice

    def confirm(self) -> None:
        if self.boot_state == BootState.TRIAL:
            self.write_record(BootRecord(self.running))
            self.boot_state = BootState.CONFIRMED

    def test(self, slot: int) -> None:
        self.write_record(BootRecord(self.record().confirmed, slot, BootState.TEST_PENDING))

    def test_cancel(self) -> None:
        self.write_record(BootRecord(self.record().confirmed))
