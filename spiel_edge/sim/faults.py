"""Line faults between the virtual board and the host: bit errors, lost and repeated frames.

Every fault is recorded, so tests can compare what the host counted with what was done to
the stream: ``damaged`` holds the acquisition indices whose frames were hit (a frame whose
closing delimiter is hit merges with the next one, which is then lost as well).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Outgoing:
    """One frame the board sends; ``acquisition`` is set for STREAM_DATA frames."""

    wire: bytes
    acquisition: int | None = None
    exempt: bool = False  # simulator annotations: never damaged (they are not board traffic)


@dataclass
class FaultStats:
    flipped_bytes_out: int = 0
    flipped_bytes_in: int = 0
    dropped_frames: int = 0
    duplicated_frames: int = 0
    damaged_frames: int = 0
    damaged: set[int] = field(default_factory=set)  # acquisition indices hit by a fault


class LineFaults:
    """Applies ``ber`` (per byte, one random bit), ``drop`` and ``dup`` (per frame)."""

    def __init__(self, ber: float = 0.0, drop: float = 0.0, dup: float = 0.0, seed: int = 0):
        self.ber, self.drop, self.dup = ber, drop, dup
        self.stats = FaultStats()
        self._rng = np.random.default_rng(seed)
        self._merge_next = False  # the previous frame's delimiter was hit

    @property
    def active(self) -> bool:
        return bool(self.ber or self.drop or self.dup)

    def outgoing(self, frames: list[Outgoing]) -> bytes:
        if not self.active:
            return b"".join(f.wire for f in frames)
        out = bytearray()
        for frame in frames:
            out += self._one(frame)
        return bytes(out)

    def incoming(self, data: bytes) -> bytes:
        """Host -> board bytes (requests); only bit errors apply."""
        if not self.ber or not data:
            return data
        damaged, hits = self._flip(data)
        self.stats.flipped_bytes_in += hits
        return damaged

    def reset(self) -> None:
        """The line was cut (unplug): no frame is half-sent any more."""
        self._merge_next = False

    def _one(self, frame: Outgoing) -> bytes:
        if frame.exempt:
            self._merge_next = False  # annotations start with a delimiter: the line resyncs
            return frame.wire
        if self.drop and self._rng.random() < self.drop:
            self.stats.dropped_frames += 1
            self._mark(frame)
            return b""
        wire = frame.wire
        damaged = self._merge_next
        self._merge_next = False
        if self.ber:
            wire, hits = self._flip(wire)
            if hits:
                self.stats.flipped_bytes_out += hits
                damaged = True
                self._merge_next = wire[-1] != 0  # the delimiter itself was hit
        if damaged:
            self._mark(frame)
        if self.dup and self._rng.random() < self.dup:
            self.stats.duplicated_frames += 1
            return wire + wire
        return wire

    def _mark(self, frame: Outgoing) -> None:
        self.stats.damaged_frames += 1
        if frame.acquisition is not None:
            self.stats.damaged.add(frame.acquisition)

    def _flip(self, data: bytes) -> tuple[bytes, int]:
        hits = int(self._rng.binomial(len(data), self.ber))
        if not hits:
            return data, 0
        buf = bytearray(data)
        positions = self._rng.choice(len(buf), size=hits, replace=False)
        bits = self._rng.integers(0, 8, size=hits)
        for pos, bit in zip(positions, bits, strict=True):
            buf[pos] ^= 1 << int(bit)
        return bytes(buf), hits
