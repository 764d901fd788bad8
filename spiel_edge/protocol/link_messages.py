"""Protocol version 2 messages: time sync, telemetry (heartbeat and device logs), firmware update.

Layouts and procedures: PROTOCOL.md section 14. A board offers each group with a HELLO
capability bit (``Capability.TIME_SYNC``, ``TELEMETRY``, ``FIRMWARE_UPDATE``) and only when
the negotiated protocol version is 2 or higher; a version-1 board answers their requests
``UNSUPPORTED`` like any unknown type.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import ClassVar

from spiel_edge.protocol._codec import Message, register

__all__ = [
    "LINK_LAYOUTS",
    "BoardState",
    "BootState",
    "FwVerifyFlag",
    "SelfTest",
    "ErrorFlag",
    "FwBegin",
    "FwBeginResponse",
    "FwConfirm",
    "FwConfirmResponse",
    "FwInfo",
    "FwInfoRequest",
    "FwTest",
    "FwTestResponse",
    "FwVerify",
    "FwVerifyResponse",
    "FwWrite",
    "FwWriteResponse",
    "Heartbeat",
    "LogLevel",
    "LogMessage",
    "SlotState",
    "Telemetry",
    "TelemetryResponse",
    "TimeSync",
    "TimeSyncResponse",
]

TIME_SYNC = 0x0006
TELEMETRY, HEARTBEAT, LOG = 0x0030, 0x0031, 0x0032
FW_INFO, FW_BEGIN, FW_WRITE, FW_VERIFY, FW_TEST, FW_CONFIRM = range(0x0040, 0x0046)
SHA256_SIZE = 32


class BoardState(IntEnum):
    """HEARTBEAT ``state``."""

    IDLE = 0
    STREAMING = 1
    UPDATING = 2  # a firmware image is being received
    ERROR = 3


class ErrorFlag(IntFlag):
    """HEARTBEAT ``error_flags``: conditions present now. Unknown bits are reported, not fatal."""

    NONE = 0
    FLASH = 0x01  # a flash write or verify failed since boot
    OVERRUN = 0x02  # acquisitions were skipped in the last period
    RX_ERRORS = 0x04  # the board's decoder dropped frames in the last period
    SENSOR = 0x08  # a transducer did not answer
    TRIAL_IMAGE = 0x10  # running a test image that is not confirmed yet (rolls back at reset)
    DEFAULT_CONFIG = 0x20  # no valid config slot: factory defaults in use
    LOG_DROPPED = 0x40  # log lines were dropped by the board's own rate limit


KNOWN_ERROR_FLAGS = int(
    ErrorFlag.FLASH
    | ErrorFlag.OVERRUN
    | ErrorFlag.RX_ERRORS
    | ErrorFlag.SENSOR
    | ErrorFlag.TRIAL_IMAGE
    | ErrorFlag.DEFAULT_CONFIG
    | ErrorFlag.LOG_DROPPED
)


class LogLevel(IntEnum):
    """LOG ``level``: syslog severities (lower is more severe)."""

    EMERG = 0
    ALERT = 1
    CRIT = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


class SlotState(IntEnum):
    """FW_INFO per-slot state."""

    EMPTY = 0  # erased or never written
    PARTIAL = 1  # being written, or an interrupted write: never booted
    VERIFIED = 2  # complete, length, CRC-32C and SHA-256 checked against FW_BEGIN
    INVALID = 3  # holds bytes that fail the image checks


class BootState(IntEnum):
    """FW_INFO ``boot_state``: where the running image stands (MCUboot's test/confirm)."""

    CONFIRMED = 0  # the running image is the permanent one
    TRIAL = 1  # running a test image once: FW_CONFIRM keeps it, a reset rolls back
    TEST_PENDING = 2  # FW_TEST accepted: the other slot boots once at the next reset


class FwVerifyFlag(IntEnum):
    """FW_VERIFY request ``flags``."""

    ASYNC = 0x01  # answer BUSY while checking; the result to the FW_VERIFY after it is done


class SelfTest(IntEnum):
    """FW_INFO ``selftest``: a trial image's self-test (the sensor answers and a first
    acquisition completes); FW_CONFIRM is refused until it PASSED."""

    NONE = 0  # not a trial (or a board from before the self-test: byte 3 was 0)
    PENDING = 1  # not started yet (waits for a stream to end)
    RUNNING = 2  # the first acquisition is in flight
    PASSED = 3  # the trial may be confirmed
    FAILED = 4  # the trial resets itself and the boot stage rolls it back


# --- time sync --------------------------------------------------------------------------


@register
@dataclass(frozen=True)
class TimeSync(Message):
    """Host -> device: the host's clock when it sent the request (MAVLink TIMESYNC ts1)."""

    MSG_TYPE: ClassVar[int] = TIME_SYNC
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<Q")
    host_time_us: int = 0  # echoed back unchanged


@register
@dataclass(frozen=True)
class TimeSyncResponse(Message):
    """The device's clock (the timestamp_us clock of STREAM_DATA) when it handled the request."""

    MSG_TYPE: ClassVar[int] = TIME_SYNC
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<QQI")
    host_time_us: int = 0  # the request's, echoed
    board_time_us: int = 0  # device clock, us since boot, when the request was handled
    boot_id: int = 0  # as in HELLO: a change means the board's clock restarted


# --- telemetry: heartbeat and device logs ----------------------------------------------


@register
@dataclass(frozen=True)
class Telemetry(Message):
    """Host -> device: the heartbeat period and the least severe log level to send."""

    MSG_TYPE: ClassVar[int] = TELEMETRY
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<HBB")
    heartbeat_ms: int = 1000  # 0 = no heartbeat
    log_level: int = LogLevel.INFO  # send LOG lines of this severity or more severe
    log_per_s: int = 20  # at most this many LOG frames per second (0 = none)


@register
@dataclass(frozen=True)
class TelemetryResponse(Message):
    MSG_TYPE: ClassVar[int] = TELEMETRY
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<HBB")
    heartbeat_ms: int = 1000  # in effect (the device may round)
    log_level: int = LogLevel.INFO
    log_per_s: int = 20


@register
@dataclass(frozen=True)
class Heartbeat(Message):
    """Device -> host, unsolicited (flags 0, seq 0): alive, idle or streaming."""

    MSG_TYPE: ClassVar[int] = HEARTBEAT
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IBBHIIQ")
    uptime_ms: int = 0  # wraps after 49.7 days
    state: int = BoardState.IDLE
    reserved: int = 0
    period_ms: int = 0  # the period in effect: the host expects the next one by then
    error_flags: int = 0  # ErrorFlag bits
    boot_id: int = 0
    board_time_us: int = 0  # device clock when it was sent


@register
@dataclass(frozen=True)
class LogMessage(Message):
    """Device -> host, unsolicited (flags 0, seq 0): one log line."""

    MSG_TYPE: ClassVar[int] = LOG
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BIQH")
    _TAIL: ClassVar[str] = "text"
    _TAIL_IS_TEXT: ClassVar[bool] = True
    level: int = LogLevel.INFO
    dropped: int = 0  # lines the device dropped (rate limit, full queue) since its last LOG
    board_time_us: int = 0
    text: str = ""  # UTF-8, at most 200 bytes


# --- firmware update --------------------------------------------------------------------


@register
@dataclass(frozen=True)
class FwInfoRequest(Message):
    MSG_TYPE: ClassVar[int] = FW_INFO


@register
@dataclass(frozen=True)
class FwInfo(Message):
    MSG_TYPE: ClassVar[int] = FW_INFO
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BBBBI16sB16sIIB16sII")
    running_slot: int = 0
    boot_state: int = BootState.CONFIRMED
    confirmed_slot: int = 0  # the slot a reset boots when no test is pending (0xFF: built-in image)
    selftest: int = SelfTest.NONE  # the trial's self-test (was reserved, 0)
    slot_size: int = 0  # bytes an image may take (header included)
    target: str = ""  # the image target this board runs, e.g. "posix", "mps2-an386", "sim"
    slot0_state: int = SlotState.EMPTY
    slot0_version: str = ""
    slot0_size: int = 0
    slot0_crc: int = 0  # CRC-32C of the whole image
    slot1_state: int = SlotState.EMPTY
    slot1_version: str = ""
    slot1_size: int = 0
    slot1_crc: int = 0


@register
@dataclass(frozen=True)
class FwBegin(Message):
    """Start an upload into the inactive slot (erases it)."""

    MSG_TYPE: ClassVar[int] = FW_BEGIN
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIH")
    _TAIL: ClassVar[str] = "sha256"
    image_size: int = 0  # bytes of the whole image, header included
    image_crc: int = 0  # CRC-32C of the whole image
    sha256: bytes = b""  # SHA-256 of the whole image, 32 bytes


@register
@dataclass(frozen=True)
class FwBeginResponse(Message):
    MSG_TYPE: ClassVar[int] = FW_BEGIN
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BI")
    slot: int = 0  # the slot being written
    slot_size: int = 0


@register
@dataclass(frozen=True)
class FwWrite(Message):
    MSG_TYPE: ClassVar[int] = FW_WRITE
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IH")
    _TAIL: ClassVar[str] = "data"
    offset: int = 0  # = the response's ``written`` so far (a repeat of an earlier chunk is OK)
    data: bytes = b""  # at most max_payload - 6 bytes


@register
@dataclass(frozen=True)
class FwWriteResponse(Message):
    MSG_TYPE: ClassVar[int] = FW_WRITE
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<I")
    written: int = 0  # bytes of the image in the slot, contiguous from 0


@register
@dataclass(frozen=True)
class FwVerify(Message):
    """Check the uploaded image: length, CRC-32C, SHA-256, its header and signature.
    ``flags`` ``FwVerifyFlag.ASYNC``: the board answers BUSY while it checks, in its main loop
    after the answer went out, and the host asks again until the result (PROTOCOL.md § 14.3);
    0 (what hosts before it sent: an empty payload) checks within the request."""

    MSG_TYPE: ClassVar[int] = FW_VERIFY
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")
    flags: int = 0


@register
@dataclass(frozen=True)
class FwVerifyResponse(Message):
    MSG_TYPE: ClassVar[int] = FW_VERIFY
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BIIH")
    _TAIL: ClassVar[str] = "sha256"
    slot: int = 0
    image_size: int = 0
    image_crc: int = 0  # as computed by the device from the slot
    sha256: bytes = b""  # as computed by the device from the slot


@register
@dataclass(frozen=True)
class FwTest(Message):
    """Boot the verified slot once after ``delay_ms`` (answered first)."""

    MSG_TYPE: ClassVar[int] = FW_TEST
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<H")
    delay_ms: int = 100


@register
@dataclass(frozen=True)
class FwTestResponse(Message):
    MSG_TYPE: ClassVar[int] = FW_TEST
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")
    slot: int = 0  # the slot that boots next


@register
@dataclass(frozen=True)
class FwConfirm(Message):
    """Make the running image permanent (idempotent)."""

    MSG_TYPE: ClassVar[int] = FW_CONFIRM


@register
@dataclass(frozen=True)
class FwConfirmResponse(Message):
    MSG_TYPE: ClassVar[int] = FW_CONFIRM
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BB")
    slot: int = 0  # the confirmed (running) slot
    boot_state: int = BootState.CONFIRMED


# Fixed parts the C header renders as packed layouts: (C prefix, class).
LINK_LAYOUTS: tuple[tuple[str, type[Message]], ...] = (
    ("sp_time_sync", TimeSync),
    ("sp_time_sync_response", TimeSyncResponse),
    ("sp_telemetry", Telemetry),
    ("sp_heartbeat", Heartbeat),
    ("sp_log", LogMessage),
    ("sp_fw_info", FwInfo),
    ("sp_fw_begin", FwBegin),
    ("sp_fw_begin_response", FwBeginResponse),
    ("sp_fw_write", FwWrite),
    ("sp_fw_verify_response", FwVerifyResponse),
    ("sp_fw_test", FwTest),
    ("sp_fw_confirm_response", FwConfirmResponse),
)
