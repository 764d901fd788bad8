"""Per-target error model of the 3-D covariance (``[scene] error_model``; docs/scene.md).

The linearised covariance (stages/uncertainty.py, one global scale and floor per mode) is
multiplied per target by k^2, with

    log k = w0 + w1 range/100 mm + w2 angle from the facing (rad) + w3 log(mean alpha / 100)
            + w4 residual/10 mm + w5 (1 - mean echo confidence)

over the target's matched echoes, then by the mode's calibration factor (a captured background,
or none): ``error_model = [w0, w1, w2, w3, w4, w5, factor_background, factor_none]``. Fitted on
held-out positions by tools/train/fit_error_model.py; empty (the default): off, covariances as
the scale and floor give them.
"""

from __future__ import annotations

import math

import numpy as np

N_VALUES = 8


def target_factor(model, position_mm, facing, residual_mm, alphas, confidences, captured) -> float:
    """k^2 x the mode's factor for one target."""
    w = model
    r = float(np.linalg.norm(position_mm))
    cosine = float(np.dot(position_mm, facing)) / r if r > 0 else 1.0
    angle = math.acos(min(max(cosine, -1.0), 1.0))
    alpha = max(float(np.mean(alphas)), 1e-6) if len(alphas) else 1e-6
    miss = 1.0 - float(np.mean(confidences)) if len(confidences) else 1.0
    log_k = (
        w[0]
        + w[1] * r / 100.0
        + w[2] * angle
        + w[3] * math.log(alpha / 100.0)
        + w[4] * residual_mm / 10.0
        + w[5] * miss
    )
    log_k = min(max(log_k, -10.0), 10.0)  # a bounded factor: e^20 at most on the variance
    return math.exp(2.0 * log_k) * (w[6] if captured else w[7])


def apply_error_model(result, model, facing, captured: bool):
    """Scale every target's covariance of ``result`` by its factor (in place); returns it."""
    feats = result.features
    for target in result.targets:
        rows = [(c, m) for c, m in enumerate(target.matched) if m is not None]
        alphas = [feats[c, m, 0] for c, m in rows]
        confidences = [feats[c, m, 4] for c, m in rows]
        factor = target_factor(
            model, target.position_mm, facing, target.residual_mm, alphas, confidences, captured
        )
        target.covariance_mm2 = target.covariance_mm2 * factor
    return result
