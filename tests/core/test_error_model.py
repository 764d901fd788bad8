"""The per-target error model of the 3-D covariance ([scene] error_model): off by default
(covariances as before), the same on the staged and the compiled path, each target's
covariance scaled by its factor (checked against a direct numpy computation)."""

import dataclasses

import numpy as np
import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.pipeline.compiled.fused import FusedPipeline
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.profile.schema import profile_from_dict, profile_to_dict

MODEL = (-1.47, 0.37, 1.82, -0.34, -0.05, -3.53, 1.97, 0.40)


def _with_model(profile, model=MODEL):
    return profile.replace(scene=dataclasses.replace(profile.scene, error_model=model))


def _factor(model, target, features, facing, captured):
    """The model written out in numpy, for one target."""
    rows = [(c, m) for c, m in enumerate(target.matched) if m is not None]
    p = target.position_mm
    r = np.linalg.norm(p)
    angle = np.arccos(np.clip(p @ facing / r, -1, 1))
    alpha = np.mean([features[c, m, 0] for c, m in rows])
    miss = 1 - np.mean([features[c, m, 4] for c, m in rows])
    w = np.array(model)
    log_k = w[:6] @ [1, r / 100, angle, np.log(alpha / 100), target.residual_mm / 10, miss]
    return np.exp(2 * log_k) * (w[6] if captured else w[7])


def test_model_scales_each_target_as_written(profile, subset):
    plain = Pipeline(profile)
    modelled = Pipeline(_with_model(profile))
    fast = FusedPipeline(Pipeline(_with_model(profile)))
    assert not fast.fallback
    checked = 0
    for f, b in list(zip(subset.frames, subset.backgrounds, strict=True))[:40]:
        for bg in (b, None):
            base = plain.process(f, bg)
            got = modelled.process(f, bg)
            assert [t.record() for t in fast.process(f, bg).targets] == [
                t.record() for t in got.targets
            ]
            for t0, t1 in zip(base.targets, got.targets, strict=True):
                np.testing.assert_array_equal(t0.position_mm, t1.position_mm)
                k2 = _factor(MODEL, t0, base.features, profile.geometry.facing, bg is not None)
                np.testing.assert_allclose(t1.covariance_mm2, t0.covariance_mm2 * k2, rtol=1e-9)
                checked += 1
    assert checked > 40


def test_mode_factors_alone(profile, subset):
    f, b = subset.frames[0], subset.backgrounds[0]
    base = Pipeline(profile)
    only = Pipeline(_with_model(profile, (0, 0, 0, 0, 0, 0, 2.0, 5.0)))
    for bg, factor in ((b, 2.0), (None, 5.0)):
        want = base.process(f, bg).targets[0].covariance_mm2 * factor
        np.testing.assert_allclose(only.process(f, bg).targets[0].covariance_mm2, want)


def test_bad_models_are_refused(profile):
    data = profile_to_dict(profile)
    for bad in ([1.0, 2.0], [0, 0, 0, 0, 0, 0, 0.0, 1.0], [0, 0, 0, 0, 0, 1e3, 1, 1]):
        data["scene"]["error_model"] = bad
        with pytest.raises(ConfigError, match="scene.error_model"):
            profile_from_dict(data)
    data["scene"]["error_model"] = list(MODEL)
    assert profile_from_dict(data).scene.error_model == MODEL
    assert profile.scene.error_model == ()  # off unless a profile or calibration sets it
