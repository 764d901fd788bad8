"""Configuration messages: chunked writes to RAM staging, read back, commit to two flash slots.

Procedure and failure semantics: PROTOCOL.md sections 6.5 and 9.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar

from spiel_edge.protocol._codec import Message, register

__all__ = [
    "ConfigCommit",
    "ConfigCommitResponse",
    "ConfigRead",
    "ConfigReadResponse",
    "ConfigSource",
    "ConfigStatus",
    "ConfigStatusRequest",
    "ConfigWrite",
    "ConfigWriteResponse",
]

CONFIG_READ, CONFIG_WRITE, CONFIG_COMMIT, CONFIG_STATUS = 0x0020, 0x0021, 0x0022, 0x0023


class ConfigSource(IntEnum):
    ACTIVE = 0  # the active flash slot
    STAGING = 1  # the RAM staging buffer


@register
@dataclass(frozen=True)
class ConfigRead(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_READ
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IHB")
    offset: int = 0
    length: int = 0  # <= max_payload - 6
    source: int = ConfigSource.ACTIVE


@register
@dataclass(frozen=True)
class ConfigReadResponse(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_READ
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IH")
    _TAIL: ClassVar[str] = "data"
    offset: int = 0
    data: bytes = b""  # shorter than asked at the end of the config


@register
@dataclass(frozen=True)
class ConfigWrite(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_WRITE
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IH")
    _TAIL: ClassVar[str] = "data"
    offset: int = 0  # offset in the RAM staging buffer; 0 starts a new staging
    data: bytes = b""


@register
@dataclass(frozen=True)
class ConfigWriteResponse(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_WRITE
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<I")
    staged_length: int = 0  # highest offset + length written since staging started


@register
@dataclass(frozen=True)
class ConfigCommit(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_COMMIT
    TIMEOUT_S: ClassVar[float] = 3.0  # erase + write + verify of a flash slot
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<II")
    total_length: int = 0
    expected_crc: int = 0  # CRC-32C of staging[0:total_length]


@register
@dataclass(frozen=True)
class ConfigCommitResponse(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_COMMIT
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BIII")
    slot: int = 0  # the slot now active
    generation: int = 0
    length: int = 0
    crc: int = 0


@register
@dataclass(frozen=True)
class ConfigStatusRequest(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_STATUS


@register
@dataclass(frozen=True)
class ConfigStatus(Message):
    MSG_TYPE: ClassVar[int] = CONFIG_STATUS
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BIIIIIBIIIB")
    active_slot: int = 0xFF  # 0 or 1; 0xFF = no valid slot (factory defaults in use)
    staged_length: int = 0
    max_length: int = 0  # capacity of a slot / the staging buffer
    slot0_generation: int = 0
    slot0_length: int = 0
    slot0_crc: int = 0
    slot0_valid: int = 0
    slot1_generation: int = 0
    slot1_length: int = 0
    slot1_crc: int = 0
    slot1_valid: int = 0
