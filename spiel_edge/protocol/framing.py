"""Framing: ``wire = COBS(body + CRC-32C(body) as u32 LE) + 0x00``, ``body = header + payload``.

Pure code: the decoder is fed bytes and returns frames; it never reads a port. It works on
whole delimiter-separated pieces (``bytes.split``) with COBS in numba kernels
(spiel_edge.protocol.cobs, with a pure fallback) and the C CRC-32C, so there is no per-byte Python loop (>= 100 MB/s, see tools/bench_protocol.py).
"""

from __future__ import annotations

import struct
from dataclasses import asdict, dataclass
from enum import IntFlag

from crc32c import crc32c

from spiel_edge.protocol import cobs
from spiel_edge.protocol.errors import FrameError

__all__ = [
    "CRC_SIZE",
    "DELIMITER",
    "HEADER",
    "HEADER_SIZE",
    "KNOWN_FLAGS",
    "MAX_ENCODED_SIZE",
    "MAX_PAYLOAD",
    "MAX_WIRE_SIZE",
    "PROTOCOL_VERSION",
    "DecoderStats",
    "Flags",
    "Frame",
    "FrameDecoder",
    "crc32c",
    "encode_frame",
    "wrap_body",
]

# The frame header's `version` byte: 1 in every protocol version so far (the framing has not
# changed); the message-layer version is negotiated by HELLO (messages.MAX_PROTOCOL_VERSION).
PROTOCOL_VERSION = 1
DELIMITER = b"\x00"
# version u8, flags u8, msg_type u16, seq u16, payload_len u16, aux u32 (little-endian)
HEADER = struct.Struct("<BBHHHI")
HEADER_SIZE = HEADER.size
CRC_SIZE = 4
# One channel of 4096 int16 samples (8192 B) plus up to 64 bytes of sub-header.
MAX_PAYLOAD = 8256
_MAX_BODY = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE
# COBS adds one code byte per started run of 254 data bytes, plus the leading one.
MAX_ENCODED_SIZE = _MAX_BODY + _MAX_BODY // 254 + 1
MAX_WIRE_SIZE = MAX_ENCODED_SIZE + 1
_MIN_BODY = HEADER_SIZE + CRC_SIZE


class Flags(IntFlag):
    """Header flag bits; any other bit set makes a receiver drop the frame."""

    NONE = 0
    RESPONSE = 0x01  # the frame answers the request with the same seq
    NACK = 0x02  # the response is an ERROR: the request failed
    ACK_REQUEST = 0x04  # the sender wants a response even for a fire-and-forget message
    STREAM = 0x08  # device-originated stream frame; aux is the stream counter
    MORE = 0x10  # more frames of the same logical response follow


KNOWN_FLAGS = int(Flags.RESPONSE | Flags.NACK | Flags.ACK_REQUEST | Flags.STREAM | Flags.MORE)
_RESPONSE = int(Flags.RESPONSE)  # a plain int: an IntFlag operation per frame costs more


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame; ``msg_type`` is not interpreted here."""

    msg_type: int
    seq: int = 0
    flags: int = 0
    aux: int = 0
    payload: bytes = b""

    @property
    def is_response(self) -> bool:
        return bool(self.flags & _RESPONSE)

    def encode(self) -> bytes:
        return encode_frame(
            self.msg_type, self.payload, seq=self.seq, flags=self.flags, aux=self.aux
        )


@dataclass(slots=True)
class DecoderStats:
    """Counters of a FrameDecoder; every dropped piece is counted under exactly one kind."""

    frames: int = 0  # frames delivered
    crc: int = 0  # CRC mismatch
    cobs: int = 0  # invalid COBS encoding
    length: int = 0  # shorter than header + CRC, or payload_len != payload length
    oversize: int = 0  # encoded piece longer than MAX_ENCODED_SIZE (discarded unread)
    version: int = 0  # unknown protocol version
    flags: int = 0  # unknown flag bit set

    @property
    def errors(self) -> int:
        return self.crc + self.cobs + self.length + self.oversize + self.version + self.flags

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _check_range(name: str, value: int, bits: int) -> None:
    if not 0 <= value < (1 << bits):
        raise FrameError(f"{name}={value} does not fit in u{bits}")


def wrap_body(body: bytes) -> bytes:
    """CRC + COBS + delimiter around an arbitrary body, unchecked (for tests and vectors)."""
    return cobs.encode(body + crc32c(body).to_bytes(4, "little")) + DELIMITER


def encode_frame(
    msg_type: int, payload: bytes = b"", *, seq: int = 0, flags: int = 0, aux: int = 0
) -> bytes:
    """Return the whole wire bytes of one frame, the trailing 0x00 delimiter included."""
    _check_range("msg_type", msg_type, 16)
    _check_range("seq", seq, 16)
    _check_range("aux", aux, 32)
    _check_range("flags", flags, 8)
    if flags & ~KNOWN_FLAGS:
        raise FrameError(f"unknown flag bits 0x{flags & ~KNOWN_FLAGS:02x}")
    if len(payload) > MAX_PAYLOAD:
        raise FrameError(f"payload of {len(payload)} bytes exceeds MAX_PAYLOAD={MAX_PAYLOAD}")
    header = HEADER.pack(PROTOCOL_VERSION, int(flags), msg_type, seq, len(payload), aux)
    return wrap_body(header + bytes(payload))


class FrameDecoder:
    """Incremental decoder: ``feed(bytes) -> list[Frame]``.

    Resynchronises at the next 0x00 after any error; buffers at most MAX_ENCODED_SIZE bytes of
    an unterminated frame (a longer run is discarded up to the next delimiter and counted as
    oversize). Never raises on input content.
    """

    def __init__(self) -> None:
        cobs.warm_up()  # numba's start-up here, not inside the first request's timeout
        self.stats = DecoderStats()
        self._partial = bytearray()
        self._discarding = False  # inside an over-long piece: drop until the next delimiter

    def reset(self) -> None:
        """Forget any partial frame (e.g. after reopening the port); stats are kept."""
        self._partial.clear()
        self._discarding = False

    @property
    def buffered(self) -> int:
        """Bytes of an unterminated frame held in the buffer."""
        return len(self._partial)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        data = bytes(data)
        last = data.rfind(0)
        if last < 0:
            self._keep(data)
            return []
        whole = data[: last + 1]  # complete pieces, each with its delimiter
        if self._discarding:  # the first piece ends an over-long one: dropped
            self._discarding = False
            whole = whole[whole.find(0) + 1 :]
        elif self._partial:
            whole = bytes(self._partial) + whole
        self._partial.clear()
        self._keep(data[last + 1 :])
        decoded = cobs.decode_pieces(whole, MAX_ENCODED_SIZE)
        if decoded is None:  # no kernels: piece by piece
            return [f for p in whole[:-1].split(DELIMITER) if p and (f := self._decode(p))]
        return self._check_all(*decoded)

    def _check_all(self, body: bytes, starts: list[int], sizes: list[int]) -> list[Frame]:
        """The pieces decoded in one kernel call: counted and checked as :meth:`_decode` does."""
        frames = []
        stats = self.stats
        for start, size in zip(starts, sizes, strict=True):
            if size < 0:
                if size == cobs.PIECE_OVERSIZE:
                    stats.oversize += 1
                elif size == cobs.PIECE_SHORT:
                    stats.cobs += 1
                continue  # PIECE_EMPTY: two delimiters in a row, nothing lost
            frame = self._checked(body[start : start + size])
            if frame is not None:
                frames.append(frame)
        return frames

    def _keep(self, tail: bytes) -> None:
        if self._discarding or not tail:
            return
        if len(self._partial) + len(tail) > MAX_ENCODED_SIZE:
            self.stats.oversize += 1
            self._partial.clear()
            self._discarding = True
        else:
            self._partial += tail

    def _decode(self, piece: bytes) -> Frame | None:
        if len(piece) > MAX_ENCODED_SIZE:
            self.stats.oversize += 1
            return None
        try:
            body = cobs.decode(piece)
        except cobs.CobsDecodeError:
            self.stats.cobs += 1
            return None
        return self._checked(body)

    def _checked(self, body: bytes) -> Frame | None:
        if len(body) < _MIN_BODY:
            self.stats.length += 1
            return None
        view = memoryview(body)
        if crc32c(view[:-CRC_SIZE]) != int.from_bytes(view[-CRC_SIZE:], "little"):
            self.stats.crc += 1
            return None
        return self._parse(body)

    def _parse(self, body: bytes) -> Frame | None:
        version, flags, msg_type, seq, payload_len, aux = HEADER.unpack_from(body)
        if version != PROTOCOL_VERSION:
            self.stats.version += 1
            return None
        if flags & ~KNOWN_FLAGS:
            self.stats.flags += 1
            return None
        if payload_len != len(body) - _MIN_BODY:
            self.stats.length += 1
            return None
        self.stats.frames += 1
        return Frame(msg_type, seq, flags, aux, body[HEADER_SIZE:-CRC_SIZE])
