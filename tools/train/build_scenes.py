"""Build scene files for ``spiel-edge evaluate``: several targets, or none captured empty.

From the spiel-icra23 recordings of one side of the position split (as in
spiel_edge.measure.evaluate.split_by_position), writes one ``.npz`` (format in
spiel_edge/measure/scenes.py) holding

- every single-target frame WITHOUT its background (the robot's case: nothing captured empty;
  with ``--single-background`` with it, the lab case);
- ``--pairs`` two-target acquisitions: the background of recording a plus the
  background-subtracted echoes (clipped at 0) of recordings a and b, whose true positions are
  at least ``--min-separation`` mm apart; the background a is given with it;
- ``--triples`` three-target acquisitions built the same way from a, b and c.

Frames labelled z = 90 mm are left out (mislabelled, see the dataset README). Use the
validation split for figures and the training split for tuning:

    python -m tools.train.build_scenes /work/shared/datasets/spiel-icra23 --split val -o val.npz
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from spiel_edge.measure.evaluate import split_by_position
from spiel_edge.recordings.spiel_csv import frame_files, position_key, read_frames, read_truth

FULL_SCALE = 65535.0
EXCLUDE_Z = (90.0,)


def load_split(root: Path, split: str):
    files = frame_files(root / "train_val")
    train, val = split_by_position([p.name for p in files])
    keep = train if split == "train" else val
    names, frames, backgrounds, truths = [], [], [], []
    for p in files:
        key = position_key(p.name)
        truth = read_truth(p)
        if key is None or key[:2] not in keep or truth is None or float(truth[2]) in EXCLUDE_Z:
            continue
        names.append(p.name)
        frames.append(read_frames(p))
        backgrounds.append(read_frames(root / "train_val_bg" / p.name))
        truths.append(truth)
    return names, np.array(frames, float), np.array(backgrounds, float), np.array(truths)


def compose(frames, backgrounds, picks):
    """Background of the first pick plus every pick's background-subtracted echoes."""
    echoes = sum(np.clip(frames[i] - backgrounds[i], 0.0, None) for i in picks)
    return np.clip(backgrounds[picks[0]] + echoes, 0.0, FULL_SCALE)


def pick_apart(rng, truths, n, min_separation, tries=1000):
    """n frame indices whose true positions are pairwise >= min_separation apart."""
    for _ in range(tries):
        picks = rng.choice(len(truths), size=n, replace=False)
        d = np.linalg.norm(truths[picks][:, None] - truths[picks][None], axis=2)
        if (d[np.triu_indices(n, 1)] >= min_separation).all():
            return [int(i) for i in picks]
    raise SystemExit(f"no {n} positions {min_separation} mm apart in this split")


def build(
    root: Path,
    split: str,
    pairs: int,
    triples: int,
    min_separation: float,
    seed: int,
    single_background: bool = False,
):
    names, frames, backgrounds, truths = load_split(root, split)
    rng = np.random.default_rng(seed)
    nan_bg = np.full(frames.shape[1:], np.nan)
    out = {"frames": [], "backgrounds": [], "truth_mm": [], "names": []}

    def add(frame, background, truth_rows, name):
        t = np.full((3, 3), np.nan)
        t[: len(truth_rows)] = truth_rows
        out["frames"].append(frame)
        out["backgrounds"].append(background)
        out["truth_mm"].append(t)
        out["names"].append(name)

    for i in range(len(names)):
        add(frames[i], backgrounds[i] if single_background else nan_bg, truths[i : i + 1], names[i])
    for n, count in ((2, pairs), (3, triples)):
        for _ in range(count):
            picks = pick_apart(rng, truths, n, min_separation)
            add(
                compose(frames, backgrounds, picks),
                backgrounds[picks[0]],
                truths[picks],
                "+".join(names[i] for i in picks),
            )
    return {k: np.array(v) for k, v in out.items()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="spiel-icra23 folder (train_val, train_val_bg)")
    ap.add_argument("--split", choices=("train", "val"), default="val")
    ap.add_argument("-o", "--out", type=Path, required=True)
    ap.add_argument("--pairs", type=int, default=300)
    ap.add_argument("--triples", type=int, default=300)
    ap.add_argument("--min-separation", type=float, default=80.0)
    ap.add_argument("--seed", type=int, default=10)
    ap.add_argument(
        "--single-background",
        action="store_true",
        help="give the single-target frames their background capture (the lab case)",
    )
    a = ap.parse_args(argv)
    scenes = build(
        a.root, a.split, a.pairs, a.triples, a.min_separation, a.seed, a.single_background
    )
    np.savez_compressed(
        a.out,
        **{k: v.astype(np.float32) if k != "names" else v for k, v in scenes.items()},
        split=a.split,
    )
    counts = np.isfinite(scenes["truth_mm"]).all(axis=2).sum(axis=1)
    print(f"{a.out}: {len(counts)} acquisitions, by targets {np.bincount(counts).tolist()}")


if __name__ == "__main__":
    main()
