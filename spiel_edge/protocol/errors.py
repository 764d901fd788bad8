"""Exceptions of the protocol package and the device error-code table.

One root, ``ProtocolError(ValueError)``: everything this package raises is a malformed value
(a bad argument, an undecodable payload) rather than an I/O failure.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = [
    "ERROR_TEXT",
    "ErrorCode",
    "FrameError",
    "MessageError",
    "ProtocolError",
    "RemoteError",
    "UnknownMessageError",
    "describe_error",
]


class ProtocolError(ValueError):
    """Root of all spiel_edge.protocol errors."""


class FrameError(ProtocolError):
    """A frame cannot be built (payload too large, field out of range, unknown flag)."""


class MessageError(ProtocolError):
    """A message payload cannot be encoded or decoded (bad field value, truncated tail)."""


class UnknownMessageError(MessageError):
    """No message class is registered for this (msg_type, response) pair."""

    def __init__(self, msg_type: int, response: bool) -> None:
        kind = "response" if response else "request"
        super().__init__(f"unknown message type 0x{msg_type:04x} ({kind})")
        self.msg_type = msg_type
        self.response = response


class ErrorCode(IntEnum):
    """Status codes a device returns in an ERROR (NACK) response, MCUmgr style."""

    OK = 0
    UNKNOWN = 1
    NO_MEMORY = 2
    INVALID = 3
    TIMEOUT = 4
    NOT_FOUND = 5
    BAD_STATE = 6
    TOO_LARGE = 7
    UNSUPPORTED = 8
    CORRUPT = 9
    BUSY = 10
    ACCESS_DENIED = 11
    VERSION_TOO_OLD = 12
    VERSION_TOO_NEW = 13
    FLASH_WRITE_FAILED = 14
    FLASH_VERIFY_FAILED = 15
    # firmware images refused for their authenticity (PROTOCOL.md § 14.6)
    FW_UNSIGNED = 16
    FW_BAD_SIGNATURE = 17
    FW_WRONG_KEY = 18
    FW_ROLLBACK = 19

    @property
    def text(self) -> str:
        return ERROR_TEXT[self]


ERROR_TEXT: dict[ErrorCode, str] = {
    ErrorCode.OK: "success",
    ErrorCode.UNKNOWN: "unknown error",
    ErrorCode.NO_MEMORY: "the device ran out of memory",
    ErrorCode.INVALID: "invalid request (a field is out of range or malformed)",
    ErrorCode.TIMEOUT: "the device timed out waiting for an internal operation",
    ErrorCode.NOT_FOUND: "the requested item does not exist",
    ErrorCode.BAD_STATE: "the request is not allowed in the device's current state",
    ErrorCode.TOO_LARGE: "the request or its data is too large",
    ErrorCode.UNSUPPORTED: "the request or message type is not supported by this firmware",
    ErrorCode.CORRUPT: "data failed its integrity check (CRC mismatch)",
    ErrorCode.BUSY: "the device is busy; retry later",
    ErrorCode.ACCESS_DENIED: "access denied",
    ErrorCode.VERSION_TOO_OLD: "the host's protocol version is too old for this firmware",
    ErrorCode.VERSION_TOO_NEW: "the host's protocol version is too new for this firmware",
    ErrorCode.FLASH_WRITE_FAILED: "writing the flash failed",
    ErrorCode.FLASH_VERIFY_FAILED: "flash read-back did not match what was written",
    ErrorCode.FW_UNSIGNED: "the firmware image is not signed; this board boots only signed images",
    ErrorCode.FW_BAD_SIGNATURE: "the firmware image's signature does not verify (tampered or truncated)",
    ErrorCode.FW_WRONG_KEY: "the firmware image is signed by a key this board does not trust",
    ErrorCode.FW_ROLLBACK: "the firmware image's security counter is below the board's (a downgrade)",
}


def describe_error(code: int) -> str:
    """Human text for any code, including ones this host does not know."""
    try:
        return ErrorCode(code).text
    except ValueError:
        return f"unrecognised device error code {code}"


class RemoteError(ProtocolError):
    """The device answered a request with an ERROR (NACK) response."""

    def __init__(self, code: int, text: str = "", request_type: int = 0) -> None:
        detail = f": {text}" if text else ""
        name = ErrorCode(code).name if code in ErrorCode._value2member_map_ else str(code)
        super().__init__(f"device error {name} ({describe_error(code)}){detail}")
        self.code = code
        self.text = text
        self.request_type = request_type
