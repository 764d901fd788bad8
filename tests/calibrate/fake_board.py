"""A fake board session for config tests: RAM staging and a two-slot flash with power cuts at
any flash operation (the same commit order as the virtual board: erase, data, header last)."""

from __future__ import annotations

from types import SimpleNamespace

from crc32c import crc32c

from spiel_edge.errors import DeviceError
from spiel_edge.protocol import ConfigSource
from spiel_edge.protocol.errors import ErrorCode


class DeviceRequestError(DeviceError):
    """Like the session's: the board answered with an error code."""

    def __init__(self, message: str, code: int = 0):
        super().__init__(message)
        self.code = code


class DeviceDisconnectedError(DeviceError):
    """The board lost power."""


class TwoSlotFlash:
    def __init__(self):
        self.slots = [None, None]  # (generation, data, crc) once the header is written
        self.data = [b"", b""]
        self.ops = 0
        self.cut_at = -1
        self.staging = b""  # the board's RAM: kept between host sessions, lost on a power cut

    def _op(self):
        if self.ops == self.cut_at:
            self.cut_at = -1
            self.staging = b""
            raise DeviceDisconnectedError(f"power lost at flash operation {self.ops}")
        self.ops += 1

    def active(self):
        valid = [
            (s[0], i)
            for i, s in enumerate(self.slots)
            if s is not None and crc32c(self.data[i]) == s[2]
        ]
        return max(valid)[1] if valid else None

    def commit(self, data: bytes):
        cur = self.active()
        target = 0 if cur is None else 1 - cur
        gen = 1 if cur is None else self.slots[cur][0] + 1
        self._op()
        self.slots[target], self.data[target] = None, b""  # erase
        for off in range(0, len(data), 256):
            self._op()
            self.data[target] += data[off : off + 256]
        self._op()
        self.slots[target] = (gen, None, crc32c(data))  # header last


class FakeBoardSession:
    def __init__(self, flash: TwoSlotFlash):
        self.flash = flash
        self.closed = False

    def read_config(self, source=ConfigSource.ACTIVE):
        if source == ConfigSource.STAGING:
            return self.staging
        slot = self.flash.active()
        if slot is None:
            raise DeviceRequestError("no valid config slot", code=ErrorCode.NOT_FOUND)
        return self.flash.data[slot]

    def write_config(self, blob, progress=None):
        self.staging = b""
        for off in range(0, len(blob), 200):
            self.staging += blob[off : off + 200]
            if progress:
                progress(len(blob[off : off + 200]))

    def commit_config(self, expected_crc):
        if crc32c(self.staging) != expected_crc:
            raise DeviceRequestError("staged data CRC mismatch", code=ErrorCode.CORRUPT)
        self.flash.commit(self.staging)

    def config_status(self):
        a = self.flash.active()
        s = [
            (x[0], len(self.flash.data[i]), x[2], 1) if x else (0, 0, 0, 0)
            for i, x in enumerate(self.flash.slots)
        ]
        return SimpleNamespace(
            active_slot=0xFF if a is None else a,
            staged_length=len(self.staging),
            max_length=4080,
            slot0_generation=s[0][0],
            slot0_length=s[0][1],
            slot0_crc=s[0][2],
            slot0_valid=s[0][3],
            slot1_generation=s[1][0],
            slot1_length=s[1][1],
            slot1_crc=s[1][2],
            slot1_valid=s[1][3],
        )

    @property
    def staging(self):
        return self.flash.staging

    @staging.setter
    def staging(self, value):
        self.flash.staging = value

    def close(self):
        self.closed = True
