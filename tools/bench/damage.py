"""Measure how much of a recording survives damage: flip one byte (or cut the file) at sampled
offsets and count the acquisitions the reader still delivers intact. Used by the hostile
test suite and ``python -m tools.bench.mcap_damage``."""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spiel_edge.recordings.mcap_reader import iter_mcap_recordings


@dataclass(frozen=True)
class DamageResult:
    offset: int
    kind: str  # "flip" or "cut"
    intact: int  # acquisitions delivered without error
    total: int  # acquisitions in the undamaged recording

    @property
    def fraction(self) -> float:
        return self.intact / self.total if self.total else 1.0


def count_intact(path: str | Path) -> int:
    return sum(r.error is None for r in iter_mcap_recordings(path))


def damage_sweep(
    path: str | Path, offsets: Iterable[int], kind: str = "flip", work: str | Path | None = None
) -> list[DamageResult]:
    """One result per offset: the byte there inverted (``flip``) or the file cut there."""
    data = Path(path).read_bytes()
    total = count_intact(path)
    results = []
    with tempfile.TemporaryDirectory(dir=work) as tmp:
        damaged = Path(tmp) / "damaged.mcap"
        for offset in offsets:
            if kind == "flip":
                buf = bytearray(data)
                buf[offset] ^= 0xFF
                damaged.write_bytes(bytes(buf))
            else:
                damaged.write_bytes(data[:offset])
            results.append(DamageResult(offset, kind, count_intact(damaged), total))
    return results


def sample_offsets(size: int, n: int, seed: int = 0, start: int = 8) -> list[int]:
    """``n`` distinct offsets spread over the file (stratified, so every region is hit)."""
    rng = np.random.default_rng(seed)
    edges = np.linspace(start, size, n + 1)
    return sorted(
        {int(rng.uniform(lo, hi)) for lo, hi in zip(edges[:-1], edges[1:], strict=True) if hi > lo}
    )
