"""Config transfer over a device session: chunked reads and writes of the board's config
blob, the commit into its two-slot flash, and its status. The blob's content is the board
config schema's business (:mod:`spiel_edge.board_config.schema`); here it is bytes."""

from __future__ import annotations

import time
from collections.abc import Callable

from spiel_edge.device.sanity import (
    CONFIG_READ_TIMEOUT_S,
    MAX_BOARD_CONFIG_BYTES,
    FirmwareError,
    board_name,
)
from spiel_edge.errors import DeviceError
from spiel_edge.protocol import (
    ConfigCommit,
    ConfigCommitResponse,
    ConfigRead,
    ConfigReadResponse,
    ConfigSource,
    ConfigStatus,
    ConfigStatusRequest,
    ConfigWrite,
    ConfigWriteResponse,
    Message,
)

CHUNK_OVERHEAD = 6  # CONFIG_READ response / CONFIG_WRITE request: u32 offset, u16 length


def _check_config_chunk(session, offset: int, got: int, asked: int, deadline: float) -> None:
    """An endless or oversized config (a firmware that answers every CONFIG_READ with a full
    chunk), or a read that takes too long, is a FirmwareError naming the board."""
    who = board_name(getattr(session, "url", "board"), getattr(session, "hello", None))
    if got > asked:
        raise FirmwareError(
            f"{who}: CONFIG_READ answered {got} bytes, {asked} were asked: a firmware bug"
        )
    if offset + got > MAX_BOARD_CONFIG_BYTES:
        raise FirmwareError(
            f"{who}: its config goes on beyond {MAX_BOARD_CONFIG_BYTES} bytes (a board config is "
            "a few kB): a firmware bug; stopped reading"
        )
    if time.monotonic() > deadline:
        raise FirmwareError(
            f"{who}: reading its config took more than {CONFIG_READ_TIMEOUT_S:g} s "
            f"({offset + got} bytes so far); stopped reading"
        )


class ConfigTransferMixin:
    """Mixed into DeviceSession; needs ``request(msg) -> Message``."""

    _staged_length: int | None = None
    max_payload: int  # of the link, from HELLO (the session sets it)

    @property
    def config_chunk(self) -> int:
        """Bytes per CONFIG_READ/WRITE: as many as one payload of this link carries
        (HELLO's max_payload, at least MIN_PAYLOAD, less the 6-byte offset and length)."""
        return self.max_payload - CHUNK_OVERHEAD

    def request(
        self, msg: Message, **kwargs
    ) -> Message:  # pragma: no cover - provided by the session
        raise NotImplementedError

    def read_config(self, source: int = ConfigSource.ACTIVE) -> bytes:
        """The active config (DeviceRequestError NOT_FOUND when there is none) or the staging."""
        data = bytearray()
        chunk = self.config_chunk
        deadline = time.monotonic() + CONFIG_READ_TIMEOUT_S
        while True:
            answer = self.request(ConfigRead(len(data), chunk, source))
            assert isinstance(answer, ConfigReadResponse)
            if answer.offset != len(data):
                raise DeviceError(f"CONFIG_READ answered offset {answer.offset}, asked {len(data)}")
            _check_config_chunk(self, len(data), len(answer.data), chunk, deadline)
            data += answer.data
            if len(answer.data) < chunk:
                return bytes(data)

    def write_config(self, blob: bytes, progress: Callable[[int], None] | None = None) -> None:
        """Replace the board's staging with ``blob`` (not persistent until commit_config)."""
        offset = 0
        size = self.config_chunk
        while True:
            chunk = blob[offset : offset + size]
            answer = self.request(ConfigWrite(offset, chunk))
            assert isinstance(answer, ConfigWriteResponse)
            offset += len(chunk)
            if answer.staged_length != offset:
                raise DeviceError(
                    f"the board staged {answer.staged_length} bytes, {offset} were sent"
                )
            if progress is not None and chunk:
                progress(len(chunk))
            if offset >= len(blob):
                break
        self._staged_length = len(blob)

    def commit_config(self, expected_crc: int, length: int | None = None) -> ConfigCommitResponse:
        """Make the staging persistent; the board checks ``expected_crc`` (CRC-32C) first."""
        if length is None:
            length = (
                self._staged_length
                if self._staged_length is not None
                else self.config_status().staged_length
            )
        answer = self.request(ConfigCommit(length, expected_crc))
        assert isinstance(answer, ConfigCommitResponse)
        return answer

    def config_status(self) -> ConfigStatus:
        answer = self.request(ConfigStatusRequest())
        assert isinstance(answer, ConfigStatus)
        return answer
