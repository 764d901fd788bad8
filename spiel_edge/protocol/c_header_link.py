"""The protocol version 2 part of ``c/spiel_registry.h`` (PROTOCOL.md section 14): enums, the
fixed part of every version-2 message as a packed layout, and the firmware image header."""

from __future__ import annotations

import dataclasses

from spiel_edge.protocol import image, link_messages, signing

__all__ = ["link_part"]


def _message_fields(cls: type) -> tuple[tuple[str, str, str], ...]:
    """(name, struct code, note) of a message's fixed part; a tail becomes its u16 length."""
    names = [f.name for f in dataclasses.fields(cls)]
    if cls._TAIL:
        names[names.index(cls._TAIL)] = f"{cls._TAIL}_len"
        names.append(names.pop(names.index(f"{cls._TAIL}_len")))
    codes = cls._CODES
    tail = f"; {cls._TAIL} follows ({cls._TAIL}_len bytes)" if cls._TAIL else ""
    return tuple(
        (name, code, (tail if name.endswith("_len") and tail else ""))
        for name, code in zip(names, codes, strict=True)
    )


def link_part(_enum, _defines, _layout, _c_string) -> list[str]:
    """Protocol version 2: its enums, the fixed part of each message, the image header
    (rendered with c_header's helpers, passed in)."""
    v2 = link_messages
    lines = [
        "/* ---- Protocol version 2 (PROTOCOL.md section 14) ---- */",
        "",
        "/* HEARTBEAT state */",
        *_enum("SP_BOARD_", v2.BoardState),
        "",
        "/* HEARTBEAT error_flags (a host reports unknown bits, it does not fail) */",
        *_enum("SP_EFLAG_", [f for f in v2.ErrorFlag if f.value], 2),
        "",
        "/* LOG level (syslog severities) */",
        *_enum("SP_LOG_", v2.LogLevel),
        "",
        "/* FW_INFO slot state and boot state */",
        *_enum("SP_SLOT_", v2.SlotState),
        *_enum("SP_BOOT_", v2.BootState),
        *_enum("SP_SELFTEST_", v2.SelfTest),
        *_enum("SP_FW_VERIFY_", v2.FwVerifyFlag),
        *_defines([("SP_SHA256_SIZE", f"{v2.SHA256_SIZE}u", "")]),
        "",
    ]
    for prefix, cls in v2.LINK_LAYOUTS:
        kind = "response" if cls.RESPONSE else "request or device-originated frame"
        title = f"{cls.__name__}: msg_type 0x{cls.MSG_TYPE:04X}, {kind}, fixed part"
        lines += _layout(prefix, f"{prefix}_t", title, _message_fields(cls))
    lines += [
        "/* Firmware image: this header, then body_size bytes of body, then (flags bit 0) the",
        " * signature trailer: magic, u8 sig_type, u8 0, u16 sig_len, u8[8] key_id, u8[64] sig */",
        *_defines(
            [
                ("SP_IMAGE_MAGIC", _c_string(image.IMAGE_MAGIC.decode()), "the first bytes"),
                ("SP_IMAGE_HEADER_VERSION", f"{image.IMAGE_HEADER_VERSION}u", ""),
                ("SP_IMAGE_FLAG_SIGNED", f"{image.FLAG_SIGNED}u", "a signature trailer follows"),
                (
                    "SP_SIG_MAGIC",
                    _c_string(signing.SIG_MAGIC.decode()),
                    "the trailer's first bytes",
                ),
                ("SP_SIG_TRAILER_SIZE", f"{signing.SIG_TRAILER_SIZE}u", "bytes"),
                ("SP_SIG_TYPE_ED25519", f"{signing.SIG_TYPE_ED25519}u", "over the 96-byte header"),
            ]
        ),
        "",
        *_layout(
            "sp_image_header",
            "sp_image_header_t",
            "Firmware image header",
            image.IMAGE_HEADER_FIELDS,
        ),
    ]
    return lines
