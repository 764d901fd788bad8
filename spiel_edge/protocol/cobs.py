"""COBS (Consistent Overhead Byte Stuffing), byte-identical to the ``cobs`` package.

Replaces the ``cobs`` package, which ships no wheels (on a board without a compiler pip
builds its pure fallback, ~50x slower). Two implementations with one behaviour:

- numba kernels (numba is a runtime dependency of spiel-edge, with wheels everywhere):
  hundreds of MB/s whatever the data. They are loaded by ``warm_up()``, which FrameDecoder
  calls when it is made (before any request and its timeout), not at import: a host tool that
  never decodes a stream never imports numba;
- a pure-Python implementation on whole blocks (C-level ``bytes`` split/slice/join), used
  until the kernels are loaded and when numba does not import. Its cost grows with the number
  of blocks (1 + len/254 + zero bytes): fine for random data, slow for sample data full of
  zero bytes.

tests/protocol/test_proto_cobs.py checks both against a per-byte reference.
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["CobsDecodeError", "decode", "encode"]

log = logging.getLogger(__name__)

_MAX_RUN = 254  # data bytes per block; code 0xFF = 254 bytes and no implied zero


class CobsDecodeError(ValueError):
    """The input is not a valid COBS encoding."""


def encode(data: bytes | bytearray | memoryview) -> bytes:
    """Encode ``data``; the result contains no zero byte (the delimiter is not appended)."""
    if _kernels is None:  # not loaded yet (warm_up) or no numba
        return encode_pure(data)
    # always a read-only array from bytes: one kernel signature, loaded by warm_up (a second
    # one, e.g. from a bytearray, would be compiled or loaded mid-stream)
    src = np.frombuffer(bytes(data), np.uint8)
    dst = np.empty(len(src) + len(src) // _MAX_RUN + 1, np.uint8)
    return dst[: _kernels.encode(src, dst)].tobytes()  # type: ignore[union-attr]


def decode(data: bytes | bytearray | memoryview) -> bytes:
    """Decode one COBS-encoded piece (without its delimiter); raise CobsDecodeError if invalid."""
    if _kernels is None:
        return decode_pure(data)
    data = bytes(data)
    if b"\x00" in data:
        raise CobsDecodeError(_ERRORS[_ZERO])
    src = np.frombuffer(data, np.uint8)
    dst = np.empty(len(src), np.uint8)
    size = _kernels.decode(src, dst)  # type: ignore[union-attr]
    if size < 0:
        raise CobsDecodeError(_ERRORS[size])
    return dst[:size].tobytes()


PIECE_SHORT, PIECE_OVERSIZE, PIECE_EMPTY = -2, -3, -4  # decode_pieces' size codes (-2: _SHORT)


def decode_pieces(data: bytes, max_piece: int) -> tuple[bytes, list[int], list[int]] | None:
    """Decode every zero-terminated piece of ``data`` (which ends with a zero byte) in one
    kernel call: (decoded bytes, each piece's start in them, its size or a PIECE_* code).
    None when the kernels are not loaded: decode each piece with :func:`decode`."""
    if _kernels is None:
        return None
    src = np.frombuffer(data, np.uint8)
    count = data.count(0)
    dst = np.empty(len(src), np.uint8)
    starts = np.empty(count, np.int64)
    sizes = np.empty(count, np.int64)
    _kernels.decode_pieces(src, dst, starts, sizes, max_piece)  # type: ignore[union-attr]
    return dst.tobytes(), starts.tolist(), sizes.tolist()


def encode_pure(data: bytes | bytearray | memoryview) -> bytes:
    """The pure-Python encoder (same output as encode)."""
    segments = bytes(data).split(b"\x00")
    last = len(segments) - 1
    parts: list[bytes] = []
    for index, segment in enumerate(segments):
        size = len(segment)
        start = 0
        while size - start >= _MAX_RUN:
            parts.append(b"\xff")
            parts.append(segment[start : start + _MAX_RUN])
            start += _MAX_RUN
        rest = size - start
        # a segment that ends on a full block needs no final code, except before a zero byte
        if rest or index != last or size == 0:
            parts.append(_CODES[rest + 1])
            parts.append(segment[start:])
    return b"".join(parts)


def decode_pure(data: bytes | bytearray | memoryview) -> bytes:
    """The pure-Python decoder (same result and errors as decode)."""
    data = bytes(data)
    if b"\x00" in data:
        raise CobsDecodeError(_ERRORS[_ZERO])
    size = len(data)
    parts: list[bytes] = []
    pos = 0
    while pos < size:
        code = data[pos]
        end = pos + code
        if end > size:
            raise CobsDecodeError(_ERRORS[_SHORT])
        parts.append(data[pos + 1 : end])
        if code != 0xFF and end < size:
            parts.append(b"\x00")
        pos = end
    return b"".join(parts)


_CODES = tuple(bytes((code,)) for code in range(256))
_ZERO, _SHORT = -1, -2
_ERRORS = {_ZERO: "zero byte found in input", _SHORT: "not enough input bytes for length code"}


_kernels = None
_tried = False


def kernels():
    """The numba kernels module, loaded (or compiled) on first use; None without numba."""
    global _kernels, _tried
    if not _tried:
        try:
            from spiel_edge.protocol import _cobs_numba as module
        except ImportError as exc:  # numba missing or broken: the pure code is correct, slower
            log.debug("COBS without numba (%s): pure-Python fallback", exc)
            module = None
        _kernels, _tried = module, True
    return _kernels


_warm = False


def warm_up() -> None:
    """Load (or compile) the numba kernels now, so that the first stream frame does not pay for
    it inside a request's timeout; FrameDecoder calls it. Idempotent and cheap once done."""
    global _warm
    if not _warm:
        _warm = True
        if kernels() is not None:
            sample = bytes(range(256)) * 2
            decode(encode(sample))
            decode_pieces(encode(sample) + b"\x00", 1024)
