"""Fit the per-target error model of the 3-D covariance (``[scene] error_model``,
pipeline/stages/error_model.py) on positions the pipeline was never tuned on, and measure it
on positions never used for any of its constants.

    python -m tools.train.fit_error_model DATA/train_val DATA/train_val_bg [--folds 4] [--scale-only]

Rows: the best target of every acquisition at the validation (x, y) positions of
``split_by_position`` (never used to tune the pipeline), with and without the background
(z = 90 mm left out). Groups: one per (x, y) position (the default), or ``--folds`` groups by
a hash of (x, y).

The fit (``cross_fit``): log k linear in the target's features, by Gaussian likelihood of its
Mahalanobis distance under the unscaled covariance, on all rows; then per mode (background,
none) the factor that puts the 95 % quantile of the *out-of-fold* normalised distances (each
group's from the weights fitted without it) at the chi-square bound. Cross-fitted so the
factor does not inherit the fit's optimism (errors are heavy-tailed).

The score (``nested``): each group is scored with ``cross_fit`` run on the other groups only
(weights and factors chosen without it), so every figure is on positions never used for any
constant. Also printed: the global scale's coverage on the same rows, and the final model on
the training positions (never used by its fit, but the pipeline was tuned there).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math

import numpy as np

from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.measure.evaluate import split_by_position
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.stages.error_model import target_factor
from spiel_edge.pipeline.stages.uncertainty import CHI2_95_3DOF
from spiel_edge.profile.schema import load_profile
from spiel_edge.recordings.spiel_csv import frame_files, position_key, read_recording, read_truth

# row layout: x, y, z, captured (1 background, 0 none), d2 (unscaled Mahalanobis^2), features
D2, CAPTURED, FEATURES = 4, 3, 5
MODES = (("background", 1), ("none", 0))


def collect(profile, folder, background_folder, side: str = "val"):
    """Per best target at the ``side`` ("val" or "train") positions: the rows above."""
    off = profile.replace(scene=dataclasses.replace(profile.scene, error_model=()))
    pipe = build_pipeline(off)
    files = frame_files(folder)
    train, val = split_by_position([p.name for p in files])
    keep = val if side == "val" else train
    rows = []
    for captured in (True, False):
        for path in files:
            key = position_key(path.name)
            if key is None or key[:2] not in keep or key[2] in EXCLUDED_Z_MM:
                continue
            rec = read_recording(path, background_folder if captured else None)
            if rec.frames is None:
                continue
            result = pipe.process(rec.frames, rec.background)
            if not result.targets:
                continue
            t = result.targets[0]
            e = t.position_mm - read_truth(path)
            d2 = float(e @ np.linalg.solve(t.covariance_mm2, e))
            rows.append((*key, float(captured), d2, *design(off, result, t)))
    return np.array(rows)


def design(profile, result, target) -> list[float]:
    """The target's features as the model weighs them (1, range, angle, log alpha, residual,
    miss), read back through target_factor so the two cannot disagree."""
    out = []
    for j in range(6):
        w = [0.0] * 8
        w[j], w[6], w[7] = 0.5, 1.0, 1.0  # factor = exp(feature_j)
        rows = [(c, m) for c, m in enumerate(target.matched) if m is not None]
        f = target_factor(
            w,
            target.position_mm,
            profile.geometry.facing,
            target.residual_mm,
            [result.features[c, m, 0] for c, m in rows],
            [result.features[c, m, 4] for c, m in rows],
            True,
        )
        out.append(math.log(f))
    return out


def fit_weights(rows) -> np.ndarray:
    """w maximising the Gaussian likelihood of d2 ~ k^2 chi2(3), log k = features @ w (Newton)."""
    d2, a = rows[:, D2], rows[:, FEATURES:]
    w = np.zeros(a.shape[1])
    for it in range(200):
        g = np.exp(-2 * (a @ w)) * d2
        step = np.linalg.solve((a * (2 * g)[:, None]).T @ a + 1e-6 * np.eye(len(w)), a.T @ (3 - g))
        w -= 0.5 * step if it < 5 else step
        if np.abs(step).max() < 1e-9:
            break
    return w


def normalised(rows, w) -> np.ndarray:
    """d2 / k^2: the Mahalanobis distance under the weights, before the mode's factor."""
    return rows[:, D2] / np.exp(2 * (rows[:, FEATURES:] @ w))


def out_of_fold(rows, groups) -> np.ndarray:
    """Each group's normalised distances under the weights fitted without that group."""
    out = np.empty(len(rows))
    for g in np.unique(groups):
        out[groups == g] = normalised(rows[groups == g], fit_weights(rows[groups != g]))
    return out


def cross_fit(rows, groups) -> list[float]:
    """The 8-number ``error_model``: weights on all rows, each mode's factor from the
    out-of-fold distances (95 % of them inside the chi-square bound)."""
    if len(np.unique(groups)) < 2:
        raise ValueError("cross-fitting needs rows from at least 2 groups")
    held = out_of_fold(rows, groups)
    factors = []
    for _, m in MODES:
        sel = rows[:, CAPTURED] == m
        if not sel.any():
            raise ValueError("cross-fitting needs rows of both modes (background, none)")
        factors.append(float(np.quantile(held[sel], 0.95) / CHI2_95_3DOF))
    return [float(v) for v in fit_weights(rows)] + factors


def factors(rows, model) -> np.ndarray:
    """Each row's covariance factor k^2 x its mode's factor under ``model``."""
    k2 = np.exp(2 * (rows[:, FEATURES:] @ np.array(model[:6])))
    return k2 * np.where(rows[:, CAPTURED] == 1, model[6], model[7])


def nested(rows, groups) -> np.ndarray:
    """Each row's factor from ``cross_fit`` on the other groups only (nested: the weights and
    the factors never saw the scored group)."""
    out = np.empty(len(rows))
    for g in np.unique(groups):
        inner = groups != g
        out[~inner] = factors(rows[~inner], cross_fit(rows[inner], groups[inner]))
    return out


def score(rows, k2) -> dict:
    """Per mode: 95 % coverage, its worst (x, y) position, the median radius against the
    global scale's (k), and the global scale's own coverage of the same rows."""
    out = {}
    inside = rows[:, D2] / k2 <= CHI2_95_3DOF
    for name, m in MODES:
        sel = rows[:, CAPTURED] == m
        xys = {tuple(r) for r in rows[sel, :2]}
        at = [sel & np.all(rows[:, :2] == xy, axis=1) for xy in xys]
        out[name] = {
            "acquisitions": int(sel.sum()),
            "coverage95": round(float(np.mean(inside[sel])), 4),
            "worst_position": round(min(float(np.mean(inside[s])) for s in at), 4),
            "median_radius_ratio": round(float(np.median(np.sqrt(k2[sel]))), 4),
            "coverage95_global_scale": round(float(np.mean(rows[sel, D2] <= CHI2_95_3DOF)), 4),
            "worst_position_global_scale": round(
                min(float(np.mean(rows[s, D2] <= CHI2_95_3DOF)) for s in at), 4
            ),
        }
    return out


def position_groups(rows, folds: int) -> np.ndarray:
    """One group per (x, y) (``folds`` = 0) or ``folds`` groups by a hash of (x, y)."""
    if folds == 0:
        xys = sorted({(x, y) for x, y in rows[:, :2]})
        return np.array([xys.index((x, y)) for x, y in rows[:, :2]])
    return np.array([fold(x, y, folds) for x, y in rows[:, :2]])


def fold(x, y, k) -> int:
    return hashlib.sha256(f"{x:g}:{y:g}".encode()).digest()[0] % k


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("folder")
    ap.add_argument("background")
    ap.add_argument("--profile", default="spiel-icra23")
    ap.add_argument(
        "--folds", type=int, default=0, help="groups by hash of (x, y); 0: one per position"
    )
    ap.add_argument(
        "--scale-only",
        action="store_true",
        help="no per-target features: one factor per mode on the global scale, cross-fitted",
    )
    args = ap.parse_args(argv)
    profile = load_profile(args.profile)
    rows = collect(profile, args.folder, args.background, "val")
    train = collect(profile, args.folder, args.background, "train")
    if args.scale_only:  # w1..w5 stay 0 (the ridge of fit_weights keeps the solve regular)
        rows[:, FEATURES + 1 :] = 0.0
        train[:, FEATURES + 1 :] = 0.0
    groups = position_groups(rows, args.folds)
    model = cross_fit(rows, groups)
    out = {
        "groups": int(len(np.unique(groups))),
        "validation_nested": score(rows, nested(rows, groups)),
        "training_positions": score(train, factors(train, model)),
        "error_model": [round(v, 4) for v in model],
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
