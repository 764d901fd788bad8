"""A labelled set in one ``.npz`` (the vendored ``spiel_edge/data/spiel_icra23_subset.npz``):
``frames`` and ``backgrounds`` (M, channels, samples), ``truth_mm`` (M, 3) and ``names`` (M,),
the original spiel-csv frames-file names (which carry the position, so splits by position work).

Read bounded (the archive's declared sizes and every member's header before any data), then
checked for shape and finiteness: one InputError line naming the file otherwise.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.recordings.spiel_csv import Recording, position_key
from spiel_edge.safety.limits import InputLimits, load_npz_bounded
from spiel_edge.safety.shown import shorten


@dataclass(frozen=True)
class LabelledArrays:
    names: list[str]
    frames: np.ndarray  # (M, channels, samples) float64
    backgrounds: np.ndarray | None  # the same shape, or None
    truth_mm: np.ndarray  # (M, 3)

    def __len__(self) -> int:
        return len(self.names)

    def select(self, keep: np.ndarray) -> LabelledArrays:
        keep = np.asarray(keep, dtype=bool)
        return LabelledArrays(
            [n for n, k in zip(self.names, keep, strict=True) if k],
            self.frames[keep],
            None if self.backgrounds is None else self.backgrounds[keep],
            self.truth_mm[keep],
        )

    def recordings(self, source: str = "") -> Iterator[Recording]:
        """Each acquisition as a Recording carrying its truth (``source#name``)."""
        for i, name in enumerate(self.names):
            bg = None if self.backgrounds is None else self.backgrounds[i]
            yield Recording(
                f"{source}#{name}" if source else name,
                self.frames[i],
                bg,
                truth_mm=self.truth_mm[i],
            )


def load_labelled(
    path: str | Path,
    limits: InputLimits | None = None,
    *,
    positions: set | None = None,
    exclude_z: Iterable[float] = (),
) -> LabelledArrays:
    """The labelled set at ``path``; ``positions`` keeps those (x, y); heights in
    ``exclude_z`` are left out."""
    path = Path(path)
    shown = shorten(path)
    data = load_npz_bounded(path, "scenes", text_ok=True)
    try:
        frames, bgs, truth, names = (
            data[k] for k in ("frames", "backgrounds", "truth_mm", "names")
        )
    except KeyError as exc:
        raise InputError(f"{shown}: not a labelled set (no {exc} array)") from None
    if frames.ndim != 3 or bgs.shape != frames.shape:
        raise InputError(
            f"{shown}: frames {frames.shape} and backgrounds {bgs.shape} must both be "
            "(acquisitions, channels, samples)"
        )
    m = len(frames)
    if truth.shape != (m, 3) or names.shape != (m,) or names.dtype.kind not in "US":
        raise InputError(
            f"{shown}: truth_mm {truth.shape} and names {names.shape} must be ({m}, 3) and ({m},)"
        )
    if m == 0:
        raise InputError(f"{shown}: no acquisitions")
    (limits or InputLimits()).check_shape(frames.shape[1], frames.shape[2])
    frames = frames.astype(np.float64)
    bgs = bgs.astype(np.float64)
    truth = truth.astype(np.float64)
    if not (np.isfinite(frames).all() and np.isfinite(truth).all()):
        raise InputError(f"{shown}: frames or truth_mm hold missing or non-finite values")
    has_bg = np.isfinite(bgs).all(axis=(1, 2))
    if has_bg.any() and not has_bg.all():
        raise InputError(f"{shown}: some acquisitions have a background and some do not")
    out = LabelledArrays([str(n) for n in names], frames, bgs if has_bg.all() else None, truth)
    skip = {float(z) for z in exclude_z}
    keep = np.array([float(t[2]) not in skip for t in truth])
    if positions is not None:
        keys = [position_key(n) for n in out.names]
        keep &= np.array([k is not None and k[:2] in positions for k in keys])
    return out.select(keep)
