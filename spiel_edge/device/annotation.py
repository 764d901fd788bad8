"""ANNOTATION: a vendor extension that simulators and test rigs send beside the stream.

Not part of spiel_edge.protocol (a real board never sends it): msg_type 0x8A01, in the range
PROTOCOL.md reserves for vendor experiments (0x8000-0xFFFF), flags 0, ``aux`` = acquisition index.
It carries the ground truth of an acquisition and, when it changed, the target-free
background of the scene, one channel per frame (the host subtracts it). Senders put a 0x00
before it so it always starts on a frame boundary. A host that does not know it ignores it.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from spiel_edge.protocol import MAX_PAYLOAD, Message, encode_frame

ANNOTATION_TYPE = 0x8A01
NO_TRUTH = math.nan


@dataclass(frozen=True)
class Annotation(Message):
    MSG_TYPE: ClassVar[int] = ANNOTATION_TYPE
    # acquisition u32, truth x/y/z f32 (mm, NaN: unknown), n_channels u8 (rows of the whole
    # background, 0: none here), first_channel u8, n_samples u16 (per row), then the byte
    # length u16 of the tail: rows first_channel.. of the background, uint16 little-endian
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IfffBBHH")
    _TAIL: ClassVar[str] = "background"
    acquisition: int = 0
    truth_x: float = NO_TRUTH
    truth_y: float = NO_TRUTH
    truth_z: float = NO_TRUTH
    n_channels: int = 0
    first_channel: int = 0
    n_samples: int = 0
    background: bytes = b""

    @property
    def truth_mm(self) -> np.ndarray | None:
        xyz = (self.truth_x, self.truth_y, self.truth_z)
        if not (math.isfinite(xyz[0]) and math.isfinite(xyz[1]) and math.isfinite(xyz[2])):
            return None
        return np.array(xyz, dtype=np.float64)

    def background_rows(self) -> np.ndarray:
        """The rows this frame carries, (rows, n_samples) uint16 (empty when malformed)."""
        if not self.n_samples or len(self.background) % (2 * self.n_samples):
            return np.zeros((0, max(self.n_samples, 1)), dtype=np.uint16)
        return np.frombuffer(self.background, "<u2").reshape(-1, self.n_samples)


def encode_annotations(
    acquisition: int, truth_mm: np.ndarray | None, background: np.ndarray | None
) -> list[bytes]:
    """Wire bytes (each with a leading 0x00) of the annotations of one acquisition: one
    frame with the truth, plus the background rows when given (as few frames as fit)."""
    truth = (NO_TRUTH,) * 3 if truth_mm is None else tuple(float(v) for v in truth_mm)
    if background is None:
        msgs = [Annotation(acquisition, *truth)]
    else:
        rows = np.ascontiguousarray(background, dtype="<u2")
        n_rows, n_samples = rows.shape
        per_frame = max(1, (MAX_PAYLOAD - Annotation._STRUCT.size) // (2 * n_samples))
        msgs = [
            Annotation(
                acquisition,
                *truth,
                n_rows,
                first,
                n_samples,
                rows[first : first + per_frame].tobytes(),
            )
            for first in range(0, n_rows, per_frame)
        ]
    return [
        b"\x00" + encode_frame(ANNOTATION_TYPE, m.pack(), aux=acquisition & 0xFFFFFFFF)
        for m in msgs
    ]


TARGETS_TYPE = 0x8A02
MAX_TRUTH_TARGETS = 64


@dataclass(frozen=True)
class TruthTargets(Message):
    """Vendor extension 0x8A02 beside ANNOTATION: the ground truth of every target of an
    acquisition (a scene with several, e.g. ``sim://?scene=model&movers=3``); ``aux`` is the
    acquisition index, as for ANNOTATION."""

    MSG_TYPE: ClassVar[int] = TARGETS_TYPE
    # acquisition u32, the tail's byte length u16, then K x (x, y, z) float32 mm
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IH")
    _TAIL: ClassVar[str] = "positions"
    acquisition: int = 0
    positions: bytes = b""

    def positions_mm(self) -> np.ndarray | None:
        """(K, 3) float64 (K = 0: a scene without targets), or None when malformed or not
        finite."""
        if len(self.positions) % 12:
            return None
        arr = np.frombuffer(self.positions, "<f4").reshape(-1, 3).astype(np.float64)
        return arr if np.all(np.isfinite(arr)) else None


def encode_truth_targets(acquisition: int, positions_mm: np.ndarray) -> bytes:
    """Wire bytes (with a leading 0x00) of the truth of every target (at most 64)."""
    rows = np.ascontiguousarray(np.asarray(positions_mm)[:MAX_TRUTH_TARGETS], dtype="<f4")
    msg = TruthTargets(acquisition, rows.tobytes())
    return b"\x00" + encode_frame(TARGETS_TYPE, msg.pack(), aux=acquisition & 0xFFFFFFFF)
