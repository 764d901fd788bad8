"""The virtual board's config requests: chunked reads and writes of the staging buffer, the
commit into its two-slot flash (power cuts included), and the slots' status."""

from __future__ import annotations

from crc32c import crc32c

from spiel_edge.protocol import ErrorCode, ErrorResponse
from spiel_edge.protocol import messages as m
from spiel_edge.sim.flash import Flash, FlashError


class BoardConfigMixin:
    """Mixed into VirtualBoard, which owns ``flash``, ``_staging`` and ``streaming``."""

    flash: Flash
    _staging: bytearray
    streaming: bool
    max_payload: int  # of the link (HELLO)

    # --- configuration -------------------------------------------------------------------

    def _config_read(self, req: m.ConfigRead, now: float) -> m.Message:
        if req.source not in (m.ConfigSource.ACTIVE, m.ConfigSource.STAGING):
            return ErrorResponse(ErrorCode.INVALID, req.MSG_TYPE, "source must be 0 or 1")
        if req.source == m.ConfigSource.STAGING:
            data: bytes | None = bytes(self._staging)
        else:
            data = self.flash.read_active()
        if data is None:
            return ErrorResponse(ErrorCode.NOT_FOUND, req.MSG_TYPE, "no valid config slot")
        if req.length > self.max_payload - 6:
            return ErrorResponse(
                ErrorCode.TOO_LARGE, req.MSG_TYPE, f"at most {self.max_payload - 6} bytes per read"
            )
        return m.ConfigReadResponse(
            req.offset, data[req.offset : req.offset + req.length]
        )  # empty past the end

    def _config_write(self, req: m.ConfigWrite, now: float) -> m.Message:
        end = req.offset + len(req.data)
        if end > self.flash.capacity:
            return ErrorResponse(
                ErrorCode.TOO_LARGE, req.MSG_TYPE, f"config exceeds {self.flash.capacity} bytes"
            )
        if req.offset == 0:
            self._staging = bytearray()  # a new staging (zeroed: holes read as 0)
        if end > len(self._staging):
            self._staging.extend(bytes(end - len(self._staging)))
        self._staging[req.offset : end] = req.data
        return m.ConfigWriteResponse(len(self._staging))

    def _config_commit(self, req: m.ConfigCommit, now: float) -> m.Message:
        if self.streaming:
            return ErrorResponse(
                ErrorCode.BAD_STATE, req.MSG_TYPE, "stop the stream before a commit"
            )
        if not 0 < req.total_length <= len(self._staging):
            return ErrorResponse(
                ErrorCode.INVALID, req.MSG_TYPE, "total_length exceeds the staged data"
            )
        data = bytes(self._staging[: req.total_length])
        if crc32c(data) != req.expected_crc:
            return ErrorResponse(ErrorCode.CORRUPT, req.MSG_TYPE, "staged data CRC mismatch")
        try:
            info = self.flash.commit(data)  # PowerCut propagates: the board loses power
        except FlashError as exc:
            code = ErrorCode.FLASH_VERIFY_FAILED if exc.verify else ErrorCode.FLASH_WRITE_FAILED
            return ErrorResponse(code, req.MSG_TYPE, str(exc))
        self._staging = bytearray()
        return m.ConfigCommitResponse(info.slot, info.generation, info.length, info.crc)

    def _config_status(self, req: m.Message, now: float) -> m.Message:
        active = self.flash.active()
        s0, s1 = self.flash.slot_info(0), self.flash.slot_info(1)
        return m.ConfigStatus(
            0xFF if active is None else active.slot,
            len(self._staging),
            self.flash.capacity,
            s0.generation,
            s0.length,
            s0.crc,
            int(s0.valid),
            s1.generation,
            s1.length,
            s1.crc,
            int(s1.valid),
        )
