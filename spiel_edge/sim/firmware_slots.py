"""The virtual board's firmware flash: two image slots, a boot record and the boot choice.

What MCUboot's test/confirm does, modelled on the operations a power cut can interrupt: an
upload erases the inactive slot and writes it chunk by chunk; FW_TEST writes a boot record
"test slot S once"; at boot the bootloader turns a pending test into a trial (record first,
then the jump), and a trial still unconfirmed at the next boot into a rollback. The boot
record is kept twice (generation + CRC, like the config slots) so a cut while writing it
leaves the previous one. Whatever slot the record names is booted only if its image passes
``parse_image`` (length, CRC-32C, SHA-256) and ``verify_image`` (signed by the board's key,
its security counter at least the record's: PROTOCOL.md § 14.6); else the other slot, else
nothing (the board then stays in its recovery loader and answers only HELLO and FW_* requests).
FW_CONFIRM raises the record's security counter to the confirmed image's.

The factory image in slot 0 is signed with the development key (the board's default key): its
signature is stored below, as Ed25519 signatures are deterministic, so the virtual board needs
no signing library (a test signs it again with keys/dev.key and compares).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from crc32c import crc32c

from spiel_edge.protocol.image import ImageError, ImageHeader, pack_image, parse_image, verify_image
from spiel_edge.protocol.link_messages import BootState, SlotState
from spiel_edge.protocol.signing import DEV_PUBLIC_KEY
from spiel_edge.sim.flash import PowerCut

SLOT_SIZE = 64 * 1024
# magic, generation, confirmed, trial, state, 0, security counter, crc
RECORD = struct.Struct("<IIBBBBII")
RECORD_MAGIC = 0x42545053  # "SPTB"
NO_SLOT = 0xFF
TARGET = "sim"
FACTORY_VERSION = "sim-0.1.0"
SILENT_MARK = b"SIM:SILENT"  # an image body starting with this boots but never answers


FACTORY_BODY = b"SIM:OK factory firmware of the virtual board"
# the development key's signatures of the factory image's header, by its max_protocol
FACTORY_SIGNATURES = {
    1: (
        "e7016430d4f4e61a2710d8e44049f37fa8ec28413e020da1260caeb201a5b35b"
        "e0f0a5f5fe92768805e4a7fc1f4f42568778e8838a438b3a19404963035aea09"
    ),
    2: (
        "1ccf77e58b0d3e7427611741a8fbbb09d6bdbcea2b86782e2e2040136b573055"
        "b74c22436681ed1e3c3da911726ca080bbc873cbe053e1b25a45942cc148d00e"
    ),
}


class _Stored:
    """A Signer that gives a signature made beforehand (the factory image's)."""

    def __init__(self, signature: str) -> None:
        self.public_key = DEV_PUBLIC_KEY
        self._signature = bytes.fromhex(signature)

    def sign(self, message: bytes) -> bytes:
        return self._signature


def factory_image(max_protocol: int = 2) -> bytes:
    return pack_image(
        FACTORY_BODY,
        version=FACTORY_VERSION,
        target=TARGET,
        min_protocol=1,
        max_protocol=max_protocol,
        signer=_Stored(FACTORY_SIGNATURES[max_protocol]),
    )


@dataclass(frozen=True)
class BootRecord:
    confirmed: int = 0
    trial: int = NO_SLOT
    state: int = BootState.CONFIRMED  # CONFIRMED, TEST_PENDING or TRIAL
    security_counter: int = 0  # anti-rollback: no image below it is booted or accepted


class FirmwareFlash:
    """Two slots and two boot record copies; ``cut_at`` cuts power at that flash operation."""

    def __init__(
        self, *, cut_at: int = -1, factory: bytes | None = None, public_key: bytes = DEV_PUBLIC_KEY
    ):
        self.public_key = bytes(public_key)  # the key built into the board's boot stage
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
            RECORD_MAGIC,
            generation,
            record.confirmed,
            record.trial,
            record.state,
            0,
            record.security_counter,
            0,
        )[:-4]
        self._op()  # erase + program of one small sector, one operation
        self._records[copy][:] = body + crc32c(body).to_bytes(4, "little")

    # --- reading ---------------------------------------------------------------------------

    def _newest(self) -> tuple[int, BootRecord] | None:
        best = None
        for raw in self._records:
            magic, gen, confirmed, trial, state, _, counter, crc = RECORD.unpack(raw)
            if magic != RECORD_MAGIC or crc32c(bytes(raw[:-4])) != crc:
                continue
            if best is None or gen > best[0]:
                best = (gen, BootRecord(confirmed, trial, state, counter))
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

    def bootable(self, slot: int, floor: int) -> ImageHeader | None:
        """The header of the slot's image if the boot stage may start it: intact, signed by
        the board's key, its security counter at least ``floor``."""
        try:
            return verify_image(self.image(slot), self.public_key, floor)
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
        floor = rec.security_counter
        choice, state = rec.confirmed, BootState.CONFIRMED
        if rec.state == BootState.TEST_PENDING and rec.trial != NO_SLOT:
            if self.bootable(rec.trial, floor) is not None:
                self.write_record(BootRecord(rec.confirmed, rec.trial, BootState.TRIAL, floor))
                choice, state = rec.trial, BootState.TRIAL
            else:
                self.write_record(BootRecord(rec.confirmed, security_counter=floor))
        elif rec.state == BootState.TRIAL:  # reset before confirm: roll back
            self.write_record(BootRecord(rec.confirmed, security_counter=floor))
        if self.bootable(choice, floor) is None:
            other = 1 - choice
            if self.bootable(other, floor) is None:
                self.running, self.boot_state = NO_SLOT, BootState.CONFIRMED
                return None
            self.write_record(BootRecord(other, security_counter=floor))
            choice, state = other, BootState.CONFIRMED
        self.running, self.boot_state = choice, state
        return choice

    def confirm(self) -> None:
        """Keep the trial; the record's security counter rises to the image's (one record
        write: a power cut leaves the old record, trial and counter, or the new one)."""
        if self.boot_state == BootState.TRIAL:
            floor = self.record().security_counter
            header = self.header(self.running)
            counter = max(floor, header.security_counter if header else 0)
            self.write_record(BootRecord(self.running, security_counter=counter))
            self.boot_state = BootState.CONFIRMED

    def test(self, slot: int) -> None:
        rec = self.record()
        self.write_record(
            BootRecord(rec.confirmed, slot, BootState.TEST_PENDING, rec.security_counter)
        )

    def test_cancel(self) -> None:
        rec = self.record()
        self.write_record(BootRecord(rec.confirmed, security_counter=rec.security_counter))
