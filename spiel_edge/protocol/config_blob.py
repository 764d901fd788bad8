"""The board config blob's binary header: what the firmware reads without a TOML parser.

``blob = header (HEADER_SIZE bytes, little-endian) + the whole config as UTF-8 TOML``. Only the
byte layout lives here; what the TOML may contain (tables, ranges, cross-field rules) is the
host's schema (``spiel_edge.board_config.schema``). Layout and ranges: PROTOCOL.md section 13.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass

from spiel_edge.protocol.errors import MessageError

__all__ = [
    "ACQUISITION_KEYS",
    "HEADER",
    "HEADER_FIELDS",
    "HEADER_SIZE",
    "MAGIC",
    "VERSION",
    "BlobHeader",
    "pack_header",
    "unpack_header",
]

MAGIC = b"SPCF"
VERSION = 1
# (name, struct code, meaning); the order is the byte order of the header
HEADER_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("magic", "4s", 'the bytes "SPCF"'),
    ("version", "H", "blob layout version, = 1"),
    ("header_size", "H", "offset of the TOML text (= 36 in version 1)"),
    ("n_samples", "H", "samples per channel per acquisition"),
    ("decimation", "H", "ADC samples per stored sample"),
    ("pulse_cycles", "H", "emitter pulse length in carrier cycles"),
    ("blind_zone_samples", "H", "samples after the emission that hold no echo"),
    ("sample_rate_hz", "f", "stored sample rate, Hz"),
    ("carrier_hz", "f", "emitter carrier frequency, Hz"),
    ("gain_db", "f", "receiver gain, dB"),
    ("acquisition_rate_hz", "f", "acquisitions (pings) per second"),
    ("toml_length", "I", "bytes of UTF-8 TOML after the header"),
)
HEADER = struct.Struct("<" + "".join(code for _, code, _ in HEADER_FIELDS))
HEADER_SIZE = HEADER.size
# the [acquisition] values the header repeats, in header order
ACQUISITION_KEYS: tuple[str, ...] = tuple(name for name, _, _ in HEADER_FIELDS[3:-1])


@dataclass(frozen=True)
class BlobHeader:
    """A decoded header; nothing is checked but the length of the input."""

    magic: bytes
    version: int
    header_size: int
    acquisition: dict[str, float]  # ACQUISITION_KEYS -> value (ints for the u16 fields)
    toml_length: int


def pack_header(acquisition: Mapping[str, float], toml_length: int) -> bytes:
    """The header for a TOML text of ``toml_length`` bytes; MessageError if a value does not
    fit its field (the host's schema validates ranges before this)."""
    try:
        values = [acquisition[key] for key in ACQUISITION_KEYS]
        return HEADER.pack(MAGIC, VERSION, HEADER_SIZE, *values, toml_length)
    except KeyError as exc:
        raise MessageError(f"config blob header: missing acquisition value {exc}") from None
    except struct.error as exc:
        raise MessageError(f"config blob header: {exc}") from exc


def unpack_header(blob: bytes) -> BlobHeader:
    """The header at the start of ``blob``; MessageError if ``blob`` is shorter than it."""
    if len(blob) < HEADER_SIZE:
        raise MessageError(f"config blob of {len(blob)} bytes is shorter than its header")
    magic, version, size, *values, length = HEADER.unpack_from(blob)
    return BlobHeader(
        magic, version, size, dict(zip(ACQUISITION_KEYS, values, strict=True)), length
    )
