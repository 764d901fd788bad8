"""Fit the covariance calibration ([scene] covariance_scale, covariance_floor_mm,
covariance_scale_no_background) on TRAINING single-target scene files, out of fold.

The pipeline's covariance is ``C = s^2 L + f^2 I`` (pipeline/stages/uncertainty.py), L the
linearised covariance with s = 1, f = 0. This tool locates the best target of every
single-target acquisition once with s = 1, f = 0, then picks, on a grid, the (s, f) with the
scales with and without a background and the shared floor with the smallest summed median
ellipsoid volume whose 95 % ellipsoid holds the truth in at least ``--coverage`` of the
frames of the mean position and ``--coverage`` - 0.05 of the 10 % worst positions, in both
cases (few positions, largely systematic errors per position). Out-of-fold coverage: positions split into ``--folds`` groups by (x, y); each
group's coverage with the values fitted on the others.

    python -m tools.train.build_scenes ROOT --split train --pairs 0 --triples 0 \\
        --single-background -o train_bg1.npz
    python -m tools.train.build_scenes ROOT --split train -o train.npz
    python -m tools.train.fit_covariance train_bg1.npz train.npz
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from spiel_edge.measure.scenes import load_scenes
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.stages.uncertainty import CHI2_95_3DOF
from spiel_edge.profile.schema import load_profile
from spiel_edge.recordings.spiel_csv import position_key

SCALES = np.round(np.arange(0.3, 4.001, 0.05), 3)
FLOORS = np.arange(0.0, 20.5, 1.0)
LOW_MARGIN = 0.10  # the 10 % worst positions may fall this far below the coverage


def collect(pipeline, path: str):
    """(eigenvalues (n, 3), error in the eigenbasis squared (n, 3), (x, y) keys, true
    heights) of the best target of every single-target acquisition that has one."""
    s = load_scenes(path)
    lams, projected, keys, heights = [], [], [], []
    for frames, bg, truth, name in zip(
        s["frames"], s["backgrounds"], s["truth_mm"], s["names"], strict=True
    ):
        truths = truth[np.isfinite(truth).all(axis=1)]
        if len(truths) != 1:
            continue
        result = pipeline.process(frames, None if np.isnan(bg).all() else bg)
        if not result.targets:
            continue
        best = result.targets[0]
        lam, vec = np.linalg.eigh(best.covariance_mm2)
        lams.append(np.maximum(lam, 1e-9))
        projected.append((vec.T @ (best.position_mm - truths[0])) ** 2)
        key = position_key(str(name))
        keys.append(key[:2] if key else (0.0, 0.0))
        heights.append(float(truths[0][2]))
    return np.array(lams), np.array(projected), keys, np.array(heights)


def inside(lams, projected, scale, floor):
    """(frames,) bool: truth inside the 95 % ellipsoid of s^2 L + f^2 I."""
    var = scale**2 * lams + floor**2
    return (projected / var).sum(axis=1) <= CHI2_95_3DOF


def volume(lams, scale, floor):
    return float(np.median(np.sqrt(np.prod(scale**2 * lams + floor**2, axis=1))))


def position_coverage(case, scale, floor) -> tuple[float, float]:
    """(mean, 10th percentile) over positions of each position's coverage: errors are
    largely systematic per position (few positions), so the calibration must hold across
    positions, not only over the pooled frames."""
    hit = inside(case[0], case[1], scale, floor)
    keys = [tuple(k) for k in case[2]]
    per = [float(hit[[k == p for k in keys]].mean()) for p in sorted(set(keys))]
    return float(np.mean(per)), float(np.percentile(per, 10))


def min_scale(case, coverage, floor):
    """Smallest grid scale whose mean position coverage reaches ``coverage`` and whose 10 %
    worst positions reach ``coverage - LOW_MARGIN`` (None: none)."""
    for s in SCALES:
        mean, low = position_coverage(case, s, floor)
        if mean >= coverage and low >= coverage - LOW_MARGIN:
            return float(s)
    return None


def fit_all(bg, nobg, coverage):
    """(scale with a background, shared floor, scale without): the smallest summed median
    ellipsoid volume of both cases, each at the required worst-height coverage."""
    best = None
    for f in FLOORS:
        s, s_nb = min_scale(bg, coverage, f), min_scale(nobg, coverage, f)
        if s is None or s_nb is None:
            continue
        v = volume(bg[0], s, f) + volume(nobg[0], s_nb, f)
        if best is None or v < best[3]:
            best = (s, float(f), s_nb, v)
    if best is None:
        return float(SCALES[-1]), float(FLOORS[-1]), float(SCALES[-1])
    return best[:3]


def out_of_fold(bg, nobg, coverage, folds):
    """Coverage of each case on held-out position groups, fitted on the rest."""
    rng = np.random.default_rng(0)
    positions = sorted(set(bg[2]) | set(nobg[2]))
    group = dict(zip(positions, rng.permutation(len(positions)) % folds, strict=True))
    hits = {"background": [], "no_background": []}
    for k in range(folds):
        split = [np.array([group[p] == k for p in case[2]]) for case in (bg, nobg)]
        train = [
            (case[0][~m], case[1][~m], [k for k, t in zip(case[2], m, strict=True) if not t])
            for case, m in zip((bg, nobg), split, strict=True)
        ]
        s, f, s_nb = fit_all(*train, coverage)
        hits["background"] += list(inside(bg[0][split[0]], bg[1][split[0]], s, f))
        hits["no_background"] += list(inside(nobg[0][split[1]], nobg[1][split[1]], s_nb, f))
    return {k: round(float(np.mean(v)), 4) for k, v in hits.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("with_background", help="training scene file, singles with background")
    ap.add_argument("without_background", help="training scene file, singles without")
    ap.add_argument("--coverage", type=float, default=0.95)
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--cache", help="npz of the located targets (written, then reused)")
    args = ap.parse_args(argv)
    profile = load_profile()
    unit = dataclasses.replace(
        profile.scene, covariance_scale=1.0, covariance_floor_mm=0.0, max_targets=1
    )
    unit = dataclasses.replace(unit, covariance_scale_no_background=1.0)
    pipeline = build_pipeline(profile.replace(scene=unit))
    if args.cache and Path(args.cache).is_file():
        with np.load(args.cache, allow_pickle=False) as z:
            bg, nobg = (
                (z[f"{c}_lams"], z[f"{c}_proj"], [tuple(k) for k in z[f"{c}_keys"]], z[f"{c}_z"])
                for c in ("bg", "nobg")
            )
    else:
        bg = collect(pipeline, args.with_background)
        nobg = collect(pipeline, args.without_background)
        if args.cache:
            np.savez(
                args.cache,
                **{
                    f"{c}_{n}": np.asarray(v)
                    for c, case in (("bg", bg), ("nobg", nobg))
                    for n, v in zip(("lams", "proj", "keys", "z"), case, strict=True)
                },
            )
    s, f, s_nb = fit_all(bg, nobg, args.coverage)
    report = {
        "covariance_scale": s,
        "covariance_floor_mm": f,
        "covariance_scale_no_background": s_nb,
        "frames": {"background": len(bg[0]), "no_background": len(nobg[0])},
        "train_coverage": {
            "background": round(float(inside(bg[0], bg[1], s, f).mean()), 4),
            "no_background": round(float(inside(nobg[0], nobg[1], s_nb, f).mean()), 4),
        },
        "out_of_fold_coverage": out_of_fold(bg, nobg, args.coverage, args.folds),
    }
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
