"""Write the vendored recordings as a labelled spiel-csv folder (frames, labels, backgrounds)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_spiel_csv(subset, root: Path, indices=None) -> tuple[Path, Path]:
    frames_dir, bg_dir = root / "frames", root / "bg"
    frames_dir.mkdir(parents=True, exist_ok=True)
    bg_dir.mkdir(parents=True, exist_ok=True)
    for i in range(len(subset)) if indices is None else indices:
        name = subset.names[i]
        np.savetxt(frames_dir / name, subset.frames[i], fmt="%d")
        np.savetxt(bg_dir / name, subset.backgrounds[i], fmt="%d")
        labels = np.c_[np.arange(4), -np.ones(4), -np.ones(4), np.tile(subset.truth_mm[i], (4, 1))]
        np.savetxt(frames_dir / name.replace("_frames.csv", "_labels.csv"), labels)
    return frames_dir, bg_dir
