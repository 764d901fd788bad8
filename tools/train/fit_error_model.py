"""Fit the per-target error model of the 3-D covariance (``[scene] error_model``,
pipeline/stages/error_model.py) on positions the pipeline was never tuned on, and measure it
on positions the model itself never saw.

    python -m tools.train.fit_error_model DATA/train_val DATA/train_val_bg [--folds 4]

The validation (x, y) positions of ``split_by_position`` (never used to tune the pipeline)
are split again into ``--folds`` groups by position; each group is scored with the model
fitted on the others (with and without the background): the coverage of the 95 % ellipsoids
and their median radius against the profile's global scale. The printed ``error_model`` is
fitted on every validation position. The fit: log k linear in the target's features, by
Gaussian likelihood of its Mahalanobis distance under the unscaled covariance; then per mode
the factor that puts the 95 % quantile of the fitted distances at the chi-square bound
(errors are heavy-tailed: the likelihood alone would under-cover).
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


def collect(profile, folder, background_folder):
    """Per best target on validation positions: (x, y, z, captured, d2, features...)."""
    off = profile.replace(scene=dataclasses.replace(profile.scene, error_model=()))
    pipe = build_pipeline(off)
    files = frame_files(folder)
    _, val = split_by_position([p.name for p in files])
    rows = []
    for captured in (True, False):
        for path in files:
            key = position_key(path.name)
            if key is None or key[:2] not in val or key[2] in EXCLUDED_Z_MM:
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


def fit(rows) -> list[float]:
    captured, d2, a = rows[:, 3], rows[:, 4], rows[:, 5:]
    w = np.zeros(a.shape[1])
    for it in range(200):
        g = np.exp(-2 * (a @ w)) * d2
        step = np.linalg.solve((a * (2 * g)[:, None]).T @ a + 1e-6 * np.eye(len(w)), a.T @ (3 - g))
        w -= 0.5 * step if it < 5 else step
        if np.abs(step).max() < 1e-9:
            break
    k2 = np.exp(2 * (a @ w))
    factors = [
        float(np.quantile(d2[captured == m] / k2[captured == m], 0.95) / CHI2_95_3DOF)
        for m in (1, 0)
    ]
    return [float(v) for v in w] + factors


def factors(rows, model) -> np.ndarray:
    k2 = np.exp(2 * (rows[:, 5:] @ np.array(model[:6])))
    return k2 * np.where(rows[:, 3] == 1, model[6], model[7])


def fold(x, y, k) -> int:
    return hashlib.sha256(f"{x:g}:{y:g}".encode()).digest()[0] % k


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("folder")
    ap.add_argument("background")
    ap.add_argument("--profile", default="spiel-icra23")
    ap.add_argument("--folds", type=int, default=4)
    args = ap.parse_args(argv)
    profile = load_profile(args.profile)
    rows = collect(profile, args.folder, args.background)
    groups = np.array([fold(x, y, args.folds) for x, y in rows[:, :2]])
    k2 = np.empty(len(rows))
    for g in range(args.folds):
        k2[groups == g] = factors(rows[groups == g], fit(rows[groups != g]))
    out = {}
    for name, m in (("background", 1), ("none", 0)):
        sel = rows[:, 3] == m
        keys = {tuple(r) for r in rows[sel, :3]}
        inside = rows[:, 4] / k2 <= CHI2_95_3DOF
        worst = min(float(np.mean(inside[sel & np.all(rows[:, :3] == k, axis=1)])) for k in keys)
        out[name] = {
            "acquisitions": int(sel.sum()),
            "coverage95_unseen_positions": round(float(np.mean(inside[sel])), 4),
            "worst_position": round(worst, 4),
            "coverage95_global_scale": round(float(np.mean(rows[sel, 4] <= CHI2_95_3DOF)), 4),
            "median_radius_ratio": round(float(np.median(np.sqrt(k2[sel]))), 4),
        }
    out["error_model"] = [round(v, 4) for v in fit(rows)]
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
