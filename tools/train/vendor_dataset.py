"""Build spiel_edge/data/spiel_icra23_subset.npz from the shared spiel-icra23 recordings.

Keeps FRAMES_PER_POSITION frames (the lowest indices) of every position, with background and
ground truth, as uint16 arrays: small enough to ship in the package (< 1 MB) for the virtual
board, the demo and the tests.

    python -m tools.train.vendor_dataset ../shared/datasets/spiel-icra23
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from spiel_edge.recordings.spiel_csv import position_key, read_frames, read_truth

FRAMES_PER_POSITION = 3


def main(root: str) -> None:
    root_path = Path(root)
    by_position: dict[tuple, list[Path]] = defaultdict(list)
    for path in sorted((root_path / "train_val").glob("*_frames.csv")):
        by_position[position_key(path.name)].append(path)
    names, frames, backgrounds, truths = [], [], [], []
    for key in sorted(by_position):
        for path in by_position[key][:FRAMES_PER_POSITION]:
            names.append(path.name)
            frames.append(read_frames(path))
            backgrounds.append(read_frames(root_path / "train_val_bg" / path.name))
            truths.append(read_truth(path))
    out = Path(__file__).resolve().parents[2] / "spiel_edge" / "data" / "spiel_icra23_subset.npz"
    np.savez_compressed(
        out,
        names=np.array(names),
        frames=np.array(frames).astype(np.uint16),
        backgrounds=np.array(backgrounds).astype(np.uint16),
        truth_mm=np.array(truths),
    )
    print(f"{out}: {len(names)} acquisitions, {out.stat().st_size} bytes")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "../shared/datasets/spiel-icra23")
