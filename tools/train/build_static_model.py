"""Build spiel_edge/models/static_spiel_icra23.npz: the static scene without a background.

Per-sample median and median absolute deviation of the background captures (train_val_bg)
of the TRAINING positions only (split by (x, y) position as in spiel_edge.measure.evaluate),
so validation figures stay unseen. See spiel_edge/pipeline/stages/static_scene.py.

    python -m tools.train.build_static_model /work/shared/datasets/spiel-icra23
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from spiel_edge.measure.evaluate import split_by_position
from spiel_edge.pipeline.stages.static_scene import static_model_arrays
from spiel_edge.recordings.spiel_csv import frame_files, position_key, read_frames

OUT = Path(__file__).resolve().parents[2] / "spiel_edge" / "models" / "static_spiel_icra23.npz"


def main(root: str) -> None:
    root_path = Path(root)
    files = frame_files(root_path / "train_val")
    train, _ = split_by_position([p.name for p in files])
    captures = [
        read_frames(root_path / "train_val_bg" / p.name)
        for p in files
        if position_key(p.name)[:2] in train
    ]
    arrays = static_model_arrays(np.array(captures))
    np.savez_compressed(
        OUT, **{k: v.astype(np.float32) for k, v in arrays.items()}, captures=len(captures)
    )
    print(f"{OUT}: median and MAD of {len(captures)} training background captures")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "/work/shared/datasets/spiel-icra23")
