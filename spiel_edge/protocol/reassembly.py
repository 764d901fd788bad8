"""Reassembly of per-channel STREAM_DATA frames into whole acquisitions (pure, numpy out).

Rules (PROTOCOL.md "Streaming"): the frame counter (``aux``) increases by one per STREAM_DATA
frame, so a jump counts the missing frames as gaps. Channels of one acquisition may come in
any order, but all of them before any frame of a later acquisition; an acquisition still
incomplete when a later one starts is dropped and counted. Indices and counters wrap at 2**32.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from spiel_edge.protocol.errors import MessageError
from spiel_edge.protocol.stream_data import (
    SAMPLE_DTYPE,
    SAMPLE_SIZE,
    STREAM_HEADER,
    SampleFormat,
    StreamData,
    sample_size,
)

__all__ = ["Acquisition", "AcquisitionAssembler", "AssemblerStats"]

_MASK = 0xFFFFFFFF
_HALF = 1 << 31
MAX_COUNTER_GAP = 1 << 16  # frames; a larger jump is a reset or a corrupt counter, not loss


def _ahead(a: int, b: int) -> int:
    """How far ``a`` is after ``b`` in u32 serial arithmetic (negative if before)."""
    d = (a - b) & _MASK
    return d - (1 << 32) if d >= _HALF else d


class _Head:
    """A STREAM_DATA sub-header read in place: the fields the assembler compares, and where
    the samples are (no StreamData object, no copy of the samples until they land in the
    acquisition's array)."""

    __slots__ = (
        "acquisition",
        "channel",
        "n_channels",
        "sample_format",
        "sample_rate_hz",
        "timestamp_us",
        "buffer",
        "offset",
        "nbytes",
    )

    def __init__(self, acquisition, channel, n_channels, fmt, rate, ts, buffer, offset, nbytes):
        self.acquisition, self.channel, self.n_channels = acquisition, channel, n_channels
        self.sample_format, self.sample_rate_hz, self.timestamp_us = fmt, rate, ts
        self.buffer, self.offset, self.nbytes = buffer, offset, nbytes

    @classmethod
    def of(cls, msg: StreamData) -> _Head:
        return cls(
            msg.acquisition,
            msg.channel,
            msg.n_channels,
            msg.sample_format,
            msg.sample_rate_hz,
            msg.timestamp_us,
            msg.samples,
            0,
            len(msg.samples),
        )

    @classmethod
    def read(cls, payload: bytes) -> _Head:
        """As ``StreamData.unpack`` checks it (the same MessageError), without the copy."""
        if len(payload) < STREAM_HEADER.size:
            raise MessageError(f"STREAM_DATA of {len(payload)} bytes is shorter than its header")
        acq, ch, n_ch, fmt, hsize, rate, ts, n, _ = STREAM_HEADER.unpack_from(payload)
        if hsize < STREAM_HEADER.size:
            raise MessageError(f"STREAM_DATA header_size {hsize} < {STREAM_HEADER.size}")
        size = SAMPLE_SIZE.get(fmt)  # IntEnum keys: a plain int finds them, no enum made
        if size is None:
            sample_size(fmt)  # raises its MessageError
        nbytes = n * size
        if hsize + nbytes > len(payload):
            raise MessageError(f"STREAM_DATA declares {n} samples but is truncated")
        return cls(acq, ch, n_ch, fmt, rate, ts, payload, hsize, nbytes)


@dataclass(frozen=True)
class Acquisition:
    index: int
    timestamp_us: int
    sample_rate_hz: int
    sample_format: int
    samples: np.ndarray  # (n_channels, n_samples), dtype SAMPLE_DTYPE[sample_format];
    # I16_IQ: (n_channels, 2 * n_samples) int16, q and i interleaved

    @property
    def n_channels(self) -> int:
        return int(self.samples.shape[0])

    @property
    def n_samples(self) -> int:
        per_sample = 2 if self.sample_format == SampleFormat.I16_IQ else 1
        return int(self.samples.shape[1]) // per_sample


@dataclass(slots=True)
class AssemblerStats:
    frames: int = 0  # STREAM_DATA messages fed
    acquisitions: int = 0  # complete acquisitions returned
    gaps: int = 0  # missing counter values (lost frames)
    incomplete: int = 0  # acquisitions dropped because a channel never came
    duplicates: int = 0  # repeated counter, or a channel already received
    stale: int = 0  # frames of an acquisition older than the current one
    inconsistent: int = 0  # sub-header disagrees with the acquisition's other channels
    jumps: int = 0  # counter jumps too large to be lost frames (resynchronized, not counted)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class AcquisitionAssembler:
    """``feed(StreamData, counter) -> Acquisition | None``, or ``feed_payload(payload,
    counter)`` straight from a frame's payload (no StreamData: the samples are copied once,
    into the acquisition's array, allocated at its first channel); call ``reset()`` per
    stream."""

    def __init__(self) -> None:
        self.stats = AssemblerStats()
        self.reset()

    def reset(self, channel_mask: int = 0) -> None:
        """Forget stream state (a new STREAM_START); the stats are kept. ``channel_mask``
        (protocol version 2, a channel subset): the physical channel ids each acquisition
        carries, its rows in increasing id order; 0: ids 0 .. n_channels - 1."""
        ids = tuple(c for c in range(32) if channel_mask >> c & 1) if channel_mask else None
        self._ids: tuple[int, ...] | None = ids
        self._row_of: dict[int, int] | None = (
            None if ids is None else {c: i for i, c in enumerate(ids)}
        )
        self._next_counter: int | None = None
        self._last_done: int | None = None
        self._first: _Head | None = None
        self._have: set[int] = set()  # channels of the current acquisition received
        self._rows: np.ndarray | None = None  # its samples, (n_channels, n_samples)

    def flush(self) -> None:
        """Drop a pending partial acquisition (stream ended), counting it incomplete."""
        if self._first is not None:
            self.stats.incomplete += 1
        self._first, self._have, self._rows = None, set(), None

    def feed(self, msg: StreamData, counter: int | None = None) -> Acquisition | None:
        return self._feed(_Head.of(msg), counter)

    def feed_payload(self, payload: bytes, counter: int | None = None) -> Acquisition | None:
        """A STREAM_DATA payload as received; MessageError (before anything is counted)
        when it does not decode, as ``StreamData.unpack`` would raise."""
        return self._feed(_Head.read(payload), counter)

    def _feed(self, msg: _Head, counter: int | None) -> Acquisition | None:
        self.stats.frames += 1
        if counter is not None and not self._count(counter):
            return None
        if not self._admit(msg):
            return None
        if msg.channel in self._have:
            self.stats.duplicates += 1
            return None
        rows = self._rows
        row = msg.channel if self._row_of is None else self._row_of[msg.channel]
        rows[row] = np.frombuffer(msg.buffer, rows.dtype, rows.shape[1], msg.offset)
        self._have.add(msg.channel)
        if len(self._have) < msg.n_channels:
            return None
        return self._complete()

    def _count(self, counter: int) -> bool:
        """Track the frame counter; False for a repeated or older frame."""
        if self._next_counter is not None:
            ahead = _ahead(counter, self._next_counter)
            if ahead < 0:
                self.stats.duplicates += 1
                return False
            if ahead > MAX_COUNTER_GAP:  # counting it as lost frames would be nonsense
                self.stats.jumps += 1
            else:
                self.stats.gaps += ahead
        self._next_counter = (counter + 1) & _MASK
        return True

    def _admit(self, msg: _Head) -> bool:
        """Place ``msg`` in the current acquisition, starting a new one if it is later."""
        first = self._first
        if first is None or _ahead(msg.acquisition, first.acquisition) > 0:
            if self._last_done is not None and _ahead(msg.acquisition, self._last_done) <= 0:
                self.stats.stale += 1
                return False
            if first is not None:
                self.stats.incomplete += 1
            return self._start(msg)
        if msg.acquisition != first.acquisition:
            self.stats.stale += 1
            return False
        if not (_channel_ok(msg, self._ids) and _consistent(first, msg)):
            self.stats.inconsistent += 1
            return False
        return True

    def _start(self, msg: _Head) -> bool:
        self._first, self._have, self._rows = None, set(), None
        valid = _channel_ok(msg, self._ids) and msg.sample_format in SAMPLE_DTYPE
        if valid:
            dtype = SAMPLE_DTYPE[msg.sample_format]
            valid = msg.nbytes % dtype.itemsize == 0
        if not valid:
            self.stats.inconsistent += 1
            return False
        self._first = msg
        self._rows = np.empty((msg.n_channels, msg.nbytes // dtype.itemsize), dtype)
        return True

    def _complete(self) -> Acquisition:
        first, samples = self._first, self._rows
        assert first is not None and samples is not None
        self._last_done, self._first, self._have, self._rows = first.acquisition, None, set(), None
        self.stats.acquisitions += 1
        return Acquisition(
            first.acquisition,
            first.timestamp_us,
            first.sample_rate_hz,
            first.sample_format,
            samples,
        )


def _channel_ok(msg: _Head, ids: tuple[int, ...] | None) -> bool:
    if ids is None:
        return 0 <= msg.channel < msg.n_channels
    return msg.channel in ids and msg.n_channels == len(ids)


def _consistent(first: _Head, msg: _Head) -> bool:
    return (
        msg.n_channels == first.n_channels
        and msg.sample_format == first.sample_format
        and msg.sample_rate_hz == first.sample_rate_hz
        and msg.timestamp_us == first.timestamp_us
        and msg.nbytes == first.nbytes
    )
