"""A damage-tolerant MCAP record scanner: every readable message of a recording, in file order.

The mcap library stops at the first bad byte. This scanner reads one record at a time with
bounded reads (never more than ``Limits.max_chunk`` bytes in memory), decompresses each chunk
on its own, and on damage skips forward to the next plausible chunk header, so one flipped
byte costs at most the chunk it lies in. A zero-filled tail (a crash mid-write on some file
systems) is skipped in large steps. What was skipped is counted in :class:`ScanReport`.
"""

from __future__ import annotations

import logging
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import IO

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x03, 0x04, 0x05, 0x06
OP_METADATA, OP_DATA_END = 0x0C, 0x0F
KNOWN_OPS = frozenset(range(0x01, 0x10))
RECORD_HEAD = struct.Struct("<BQ")
_MSG = struct.Struct("<HIQQ")
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
WINDOW = 1 << 20  # resync and zero-skip read size
ZSTD_MAGIC, LZ4_MAGIC = b"\x28\xb5\x2f\xfd", b"\x04\x22\x4d\x18"


@dataclass(frozen=True)
class Limits:
    max_message: int = 8 << 20  # bytes of one message's payload
    max_chunk: int = 32 << 20  # bytes of one chunk, compressed or not


@dataclass
class ScanReport:
    chunks: int = 0  # chunks read (whole or in part)
    damaged_chunks: int = 0  # chunks read only in part (bad CRC, cut decompression)
    lost_chunks: int = 0  # chunk headers found but nothing readable inside
    skipped_bytes: int = 0  # bytes passed over while looking for the next record
    zero_bytes: int = 0  # of them, zero fill
    oversize: int = 0  # messages larger than the limit, not parsed
    truncated: bool = False  # the file ends inside a record (never finalized or cut)
    finalized: bool = False  # the data section's end marker was found
    notes: list[str] = field(default_factory=list)

    @property
    def damaged(self) -> bool:
        return bool(self.damaged_chunks or self.lost_chunks or self.skipped_bytes or self.oversize)

    def summary(self) -> str:
        parts = []
        if self.damaged_chunks:
            parts.append(f"{self.damaged_chunks} of {self.chunks} chunks damaged (read in part)")
        if self.lost_chunks:
            parts.append(f"{self.lost_chunks} chunks unreadable")
        if self.skipped_bytes:
            zeros = f", {self.zero_bytes} of them zero fill" if self.zero_bytes else ""
            parts.append(f"{self.skipped_bytes} bytes skipped{zeros}")
        if self.oversize:
            parts.append(f"{self.oversize} oversize messages skipped")
        if self.truncated:
            parts.append("the file ends inside a record (cut short)")
        elif not self.finalized:
            parts.append("the recording was never finalized")
        return "; ".join(parts) if parts else "intact"


@dataclass(frozen=True)
class RawMessage:
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes
    topic: str | None  # None when the channel record was lost


class McapScanner:
    """``for msg in McapScanner(fh, size).messages(): ...``; ``report`` says what was lost."""

    def __init__(self, fh: IO[bytes], size: int, limits: Limits | None = None) -> None:
        self.fh, self.size = fh, size
        self.limits = limits or Limits()
        self.report = ScanReport()
        self.topics: dict[int, str] = {}

    # --- the file level ------------------------------------------------------------------

    def messages(self) -> Iterator[RawMessage]:
        pos = len(MAGIC)
        while pos < self.size:
            head = self._read(pos, RECORD_HEAD.size)
            if len(head) < RECORD_HEAD.size:
                self.report.truncated = True
                return
            op, length = RECORD_HEAD.unpack(head)
            if op == OP_DATA_END:  # finalized when the file also ends with its footer and magic
                self.report.finalized = self._read(self.size - len(MAGIC), len(MAGIC)) == MAGIC
                return
            if op == 0 and length == 0:
                pos = self._skip_zeros(pos)
                continue
            end = pos + RECORD_HEAD.size + length
            if op == OP_CHUNK:
                result = self._chunk(pos)
                if result is not None:
                    next_pos, records = result
                    yield from self._records(records)
                    pos = next_pos
                    continue
            elif op in KNOWN_OPS and end <= self.size and length <= self.limits.max_chunk:
                if not self._record_starts(end):  # a damaged length: do not jump blindly
                    pos = self._resync(pos + 1)
                    continue
                if op in (OP_CHANNEL, OP_MESSAGE):
                    body = self._read(pos + RECORD_HEAD.size, length)
                    yield from self._records(bytes([op]) + struct.pack("<Q", length) + body)
                pos = end
                continue
            elif op in KNOWN_OPS and end > self.size and length <= self.limits.max_chunk:
                # the file ends inside this record, or a damaged length points past the end:
                # a chunk after it tells them apart
                skipped, pos = self.report.skipped_bytes, self._resync(pos + 1)
                if pos >= self.size:
                    self.report.skipped_bytes = skipped  # a cut file, not a damaged one
                    self.report.truncated = True
                    return
                continue
            pos = self._resync(pos + 1)

    def _read(self, pos: int, n: int) -> bytes:
        self.fh.seek(pos)
        return self.fh.read(max(0, min(n, self.size - pos)))

    def _skip_zeros(self, pos: int) -> int:
        start = pos
        while pos < self.size:
            block = self._read(pos, WINDOW)
            rest = block.lstrip(b"\0")
            pos += len(block) - len(rest)
            if rest:
                break
        self.report.skipped_bytes += pos - start
        self.report.zero_bytes += pos - start
        return pos

    def _resync(self, pos: int) -> int:
        """The next offset where a plausible chunk header starts (or the end of the file)."""
        start = pos - 1
        while pos < self.size:
            block = self._read(pos, WINDOW + 64)
            at = block.find(bytes([OP_CHUNK]))
            while 0 <= at < min(len(block), WINDOW):
                if self._plausible_chunk(block[at : at + RECORD_HEAD.size + _CHUNK.size]):
                    self.report.skipped_bytes += pos + at - start
                    return pos + at
                at = block.find(bytes([OP_CHUNK]), at + 1)
            pos += WINDOW
        self.report.skipped_bytes += self.size - start
        return self.size

    def _plausible_chunk(self, head: bytes) -> bool:
        """Whether ``head`` (bytes from a 0x06) reads as a chunk header within the limits."""
        if len(head) < RECORD_HEAD.size + _CHUNK.size:
            return False
        _op, length = RECORD_HEAD.unpack_from(head)
        start, end, usize, _crc, clen = _CHUNK.unpack_from(head, RECORD_HEAD.size)
        return (
            clen <= 8
            and start <= end
            and 0 < usize <= self.limits.max_chunk
            and 0 < length <= self.limits.max_chunk
        )

    # --- chunks --------------------------------------------------------------------------

    def _chunk(self, pos: int) -> tuple[int, bytes] | None:
        """(offset after the chunk, its decompressed records) or None when it is unusable."""
        fixed = self._read(pos, RECORD_HEAD.size + _CHUNK.size)
        if len(fixed) < RECORD_HEAD.size + _CHUNK.size:
            self.report.truncated = True
            return self.size, b""
        _op, length = RECORD_HEAD.unpack_from(fixed)
        _start, _end, usize, crc, clen = _CHUNK.unpack_from(fixed, RECORD_HEAD.size)
        if clen > 8:
            return None
        at = pos + RECORD_HEAD.size + _CHUNK.size
        compression = self._read(at, clen).decode("ascii", "replace")
        at += clen
        inner = self._read(at, 8)
        if len(inner) < 8:
            self.report.truncated = True
            return self.size, b""
        (records_len,) = struct.unpack("<Q", inner)
        at += 8
        from_outer = pos + RECORD_HEAD.size + length - at
        candidates = [n for n in (records_len, from_outer) if 0 < n <= self.limits.max_chunk]
        if not candidates:
            return None
        # the two lengths agree unless one was damaged: prefer one that ends on a record
        candidates.sort(key=lambda n: (not self._record_starts(at + n), n != records_len))
        n = candidates[0]
        data = self._read(at, n)
        self.report.chunks += 1
        cut = len(data) < n
        if cut:
            self.report.truncated = True
        records, whole = self._decompress(compression, data, usize)
        if not records:
            self.report.lost_chunks += 1
        elif cut or not whole or (crc and zlib.crc32(records) != crc):
            self.report.damaged_chunks += 1
        return at + n, records

    def _record_starts(self, pos: int) -> bool:
        if pos >= self.size:
            return pos == self.size
        head = self._read(pos, RECORD_HEAD.size)
        return len(head) == RECORD_HEAD.size and head[0] in KNOWN_OPS

    def _decompress(self, compression: str, data: bytes, usize: int) -> tuple[bytes, bool]:
        """(the records, whether decompression ran to the end); as much as could be read."""
        if compression == "zstd" or (compression not in ("", "lz4") and data[:4] == ZSTD_MAGIC):
            return _zstd(data, self.limits.max_chunk)
        if compression == "lz4" or (compression != "" and data[:4] == LZ4_MAGIC):
            return _lz4(data, self.limits.max_chunk)
        if compression == "":
            return data, True
        self.report.notes.append(f"unknown chunk compression {compression!r}")
        return b"", False

    # --- records inside a chunk (or at the top level) -----------------------------------

    def _records(self, data: bytes) -> Iterator[RawMessage]:
        pos, size = 0, len(data)
        while pos + RECORD_HEAD.size <= size:
            op, length = RECORD_HEAD.unpack_from(data, pos)
            body_at, end = pos + RECORD_HEAD.size, pos + RECORD_HEAD.size + length
            if op not in KNOWN_OPS or end > size:
                pos = self._resync_inner(data, pos + 1)
                continue
            if op == OP_CHANNEL:
                self._channel(data[body_at:end])
            elif op == OP_MESSAGE and length >= _MSG.size:
                message = self._message(data, body_at, end)
                if message is not None:
                    yield message
            pos = end

    def _resync_inner(self, data: bytes, pos: int) -> int:
        """The next message record with a known channel and a JSON object payload."""
        while True:
            at = data.find(bytes([OP_MESSAGE]), pos)
            if at < 0 or at + RECORD_HEAD.size + _MSG.size >= len(data):
                return len(data)
            _op, length = RECORD_HEAD.unpack_from(data, at)
            channel = struct.unpack_from("<H", data, at + RECORD_HEAD.size)[0]
            payload_at = at + RECORD_HEAD.size + _MSG.size
            if (
                channel in self.topics
                and _MSG.size < length <= len(data) - at - RECORD_HEAD.size
                and data[payload_at : payload_at + 1] == b"{"
            ):
                return at
            pos = at + 1

    def _channel(self, body: bytes) -> None:
        try:
            channel_id, _schema = struct.unpack_from("<HH", body)
            (n,) = struct.unpack_from("<I", body, 4)
            topic = body[8 : 8 + n].decode("utf-8")
        except (struct.error, UnicodeDecodeError):
            return
        if 0 < n <= 256 and len(body) >= 8 + n:
            self.topics[channel_id] = topic

    def _message(self, data: bytes, at: int, end: int) -> RawMessage | None:
        channel_id, sequence, log_time, publish_time = _MSG.unpack_from(data, at)
        if end - at - _MSG.size > self.limits.max_message:
            self.report.oversize += 1
            return None
        return RawMessage(
            channel_id,
            sequence,
            log_time,
            publish_time,
            data[at + _MSG.size : end],
            self.topics.get(channel_id),
        )


def _zstd(data: bytes, limit: int) -> tuple[bytes, bool]:
    import zstandard

    out = bytearray()
    decompressor = zstandard.ZstdDecompressor().decompressobj()
    try:
        for i in range(0, len(data), 1024):
            out += decompressor.decompress(data[i : i + 1024])
            if len(out) > limit:
                return bytes(out[:limit]), False
    except zstandard.ZstdError:
        return bytes(out), False
    return bytes(out), decompressor.eof


def _lz4(data: bytes, limit: int) -> tuple[bytes, bool]:
    try:
        import lz4.frame
    except ImportError:
        return b"", False
    out = bytearray()
    decompressor = lz4.frame.LZ4FrameDecompressor()
    try:
        for i in range(0, len(data), 1024):
            out += decompressor.decompress(data[i : i + 1024])
            if len(out) > limit:
                return bytes(out[:limit]), False
    except RuntimeError:
        return bytes(out), False
    return bytes(out), decompressor.eof
