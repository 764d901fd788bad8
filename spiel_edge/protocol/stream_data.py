"""STREAM_DATA: one channel of one acquisition per frame, with a 24-byte sub-header.

The sub-header carries its own size (``header_size``) so it can grow without moving the
samples; samples follow it little-endian. The frame's ``aux`` is the stream counter.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar

import numpy as np

from spiel_edge.protocol._codec import Message
from spiel_edge.protocol.errors import MessageError
from spiel_edge.protocol.framing import MAX_PAYLOAD

__all__ = [
    "MAX_SAMPLES_PER_FRAME",
    "SAMPLE_DTYPE",
    "SAMPLE_SIZE",
    "STREAM_HEADER",
    "STREAM_HEADER_FIELDS",
    "SampleFormat",
    "StreamData",
]

STREAM_DATA_TYPE = 0x0013


class SampleFormat(IntEnum):
    U16_ENVELOPE = 0  # rectified, filtered envelope, unsigned 16-bit
    I16_RF = 1  # raw RF samples, signed 16-bit
    F32 = 2  # IEEE-754 binary32 (processed on the board)
    I16_IQ = 3  # version 2: int16 (q, i) pairs, the CH101's ch_get_iq_data order


# bytes per sample; an I16_IQ sample is one (q, i) pair of int16 (4 bytes)
SAMPLE_SIZE = {
    SampleFormat.U16_ENVELOPE: 2,
    SampleFormat.I16_RF: 2,
    SampleFormat.F32: 4,
    SampleFormat.I16_IQ: 4,
}
# numpy dtype of one value: an I16_IQ channel of n samples is 2n int16 values q0 i0 q1 i1 ...
SAMPLE_DTYPE = {
    SampleFormat.U16_ENVELOPE: np.dtype("<u2"),
    SampleFormat.I16_RF: np.dtype("<i2"),
    SampleFormat.F32: np.dtype("<f4"),
    SampleFormat.I16_IQ: np.dtype("<i2"),
}
# (name, struct code, meaning); the order is the byte order of the sub-header
STREAM_HEADER_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("acquisition", "I", "acquisition index, +1 per acquisition, wraps at 2^32"),
    ("channel", "B", "0 .. n_channels - 1"),
    ("n_channels", "B", "channels in this acquisition"),
    ("sample_format", "B", "SampleFormat (SP_SAMPLE_*)"),
    ("header_size", "B", "offset of the first sample (= 24 in version 1)"),
    ("sample_rate_hz", "I", "Hz"),
    ("timestamp_us", "Q", "device clock at the acquisition's first sample, us"),
    ("n_samples", "H", "samples in this frame"),
    ("reserved", "H", "0"),
)
STREAM_HEADER = struct.Struct("<" + "".join(code for _, code, _ in STREAM_HEADER_FIELDS))
MAX_SAMPLES_PER_FRAME = {
    fmt: (MAX_PAYLOAD - STREAM_HEADER.size) // size for fmt, size in SAMPLE_SIZE.items()
}


def sample_size(sample_format: int) -> int:
    try:
        return SAMPLE_SIZE[SampleFormat(sample_format)]
    except ValueError:
        raise MessageError(f"unknown sample format {sample_format}") from None


@dataclass(frozen=True)
class StreamData(Message):
    """Device -> host (flags STREAM, unacknowledged): one channel of one acquisition."""

    MSG_TYPE: ClassVar[int] = STREAM_DATA_TYPE
    _STRUCT: ClassVar[struct.Struct] = STREAM_HEADER
    acquisition: int = 0  # index, +1 per acquisition (ping), wraps at 2**32
    channel: int = 0  # 0 .. n_channels-1
    n_channels: int = 1  # channels in this acquisition
    sample_format: int = SampleFormat.U16_ENVELOPE
    sample_rate_hz: int = 0
    timestamp_us: int = 0  # device clock at the acquisition's first sample (same per channel)
    samples: bytes = b""  # little-endian samples of sample_format

    @property
    def n_samples(self) -> int:
        return len(self.samples) // sample_size(self.sample_format)

    def samples_array(self) -> np.ndarray:
        """The samples as a read-only numpy view (dtype from ``SAMPLE_DTYPE``)."""
        return np.frombuffer(self.samples, SAMPLE_DTYPE[SampleFormat(self.sample_format)])

    def pack(self) -> bytes:
        size = sample_size(self.sample_format)
        if len(self.samples) % size:
            raise MessageError(f"{len(self.samples)} sample bytes is not a multiple of {size}")
        try:
            header = STREAM_HEADER.pack(
                self.acquisition,
                self.channel,
                self.n_channels,
                self.sample_format,
                STREAM_HEADER.size,
                self.sample_rate_hz,
                self.timestamp_us,
                len(self.samples) // size,
                0,
            )
        except struct.error as exc:
            raise MessageError(f"StreamData: {exc}") from exc
        return header + bytes(self.samples)

    @classmethod
    def unpack(cls, payload: bytes) -> StreamData:
        if len(payload) < STREAM_HEADER.size:
            raise MessageError(f"STREAM_DATA of {len(payload)} bytes is shorter than its header")
        acq, ch, n_ch, fmt, hsize, rate, ts, n, _ = STREAM_HEADER.unpack_from(payload)
        if hsize < STREAM_HEADER.size:
            raise MessageError(f"STREAM_DATA header_size {hsize} < {STREAM_HEADER.size}")
        end = hsize + n * sample_size(fmt)
        if end > len(payload):
            raise MessageError(f"STREAM_DATA declares {n} samples but is truncated")
        return cls(acq, ch, n_ch, fmt, rate, ts, bytes(payload[hsize:end]))
