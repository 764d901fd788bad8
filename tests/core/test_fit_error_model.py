"""tools/train/fit_error_model's fit on synthetic rows: the weights recovered, the mode factors
cross-fitted (out-of-fold) and so centred at 95 %, and the nested score blind to the scored
group (no data of it reaches its model)."""

import numpy as np
import pytest

from spiel_edge.pipeline.stages.uncertainty import CHI2_95_3DOF
from tools.train.fit_error_model import (
    cross_fit,
    factors,
    fit_weights,
    nested,
    out_of_fold,
    position_groups,
    score,
)

TRUE_W = np.array([-0.4, 0.3, 0.8, -0.3, 0.1, -1.0])
TRUE_FACTORS = (2.0, 0.5)  # background, none


def _rows(seed, per_mode=80, positions=6):
    """x, y, z, captured, d2, features; d2 = k^2 x factor x chi2(3) exactly as the model says."""
    rng = np.random.default_rng(seed)
    rows = []
    for p in range(positions):
        x, y = 40.0 * (p % 3), 40.0 * (p // 3)
        for captured in (1.0, 0.0):
            for _ in range(per_mode):
                a = [1.0, rng.uniform(1, 2.2), rng.uniform(0, 0.6), rng.normal(0, 1)]
                a += [rng.uniform(0, 1), rng.uniform(0, 0.3)]
                k2 = np.exp(2 * np.dot(a, TRUE_W)) * TRUE_FACTORS[captured == 0]
                rows.append([x, y, 150.0, captured, k2 * rng.chisquare(3), *a])
    return np.array(rows)


def test_weights_recovered_and_reference_likelihood_is_at_its_maximum():
    rows = _rows(1, per_mode=400)
    w = fit_weights(rows)
    np.testing.assert_allclose(w[1:], TRUE_W[1:], atol=0.12)
    # numpy reference: the gradient of the Gaussian log-likelihood vanishes at the fit
    a, d2 = rows[:, 5:], rows[:, 4]
    grad = a.T @ (np.exp(-2 * (a @ w)) * d2 - 3)
    assert np.abs(grad).max() < 1e-6 * len(rows)


def test_cross_fitted_factors_match_the_out_of_fold_quantile():
    rows = _rows(2)
    groups = position_groups(rows, 0)
    assert len(np.unique(groups)) == 6
    model = cross_fit(rows, groups)
    held = out_of_fold(rows, groups)
    for factor, m in zip(model[6:], (1, 0), strict=True):
        sel = rows[:, 3] == m
        inside = held[sel] / factor <= CHI2_95_3DOF
        assert inside.mean() == pytest.approx(0.95, abs=1.0 / sel.sum() + 1e-9)
    # the background's variance is 4x the none mode's in the data, so in the factors
    assert model[6] / model[7] == pytest.approx(4.0, rel=0.35)


def test_nested_score_is_centred_and_never_sees_the_scored_group():
    rows = _rows(3)
    groups = position_groups(rows, 0)
    k2 = nested(rows, groups)
    got = score(rows, k2)
    for mode in ("background", "none"):
        assert 0.90 <= got[mode]["coverage95"] <= 0.99
    # the scored group's own errors change: its nested factors do not (no leak)
    changed = rows.copy()
    changed[groups == 0, 4] *= 50.0
    k2b = nested(changed, groups)
    np.testing.assert_array_equal(k2b[groups == 0], k2[groups == 0])
    assert not np.array_equal(k2b[groups != 0], k2[groups != 0])


def test_factors_apply_weights_and_the_mode_factor():
    rows = _rows(4, per_mode=3, positions=2)
    model = [*TRUE_W, 2.0, 0.5]
    want = np.exp(2 * rows[:, 5:] @ TRUE_W) * np.where(rows[:, 3] == 1, 2.0, 0.5)
    np.testing.assert_allclose(factors(rows, model), want)


def test_hash_groups_and_refusals():
    rows = _rows(5, per_mode=5)
    g = position_groups(rows, 4)
    assert set(g) <= {0, 1, 2, 3}
    for xy in {(x, y) for x, y in rows[:, :2]}:  # a position never splits
        assert len(set(g[np.all(rows[:, :2] == xy, axis=1)])) == 1
    with pytest.raises(ValueError, match="2 groups"):
        cross_fit(rows, np.zeros(len(rows), int))
    with pytest.raises(ValueError, match="both modes"):
        one = rows[rows[:, 3] == 1]
        cross_fit(one, position_groups(one, 0))


def test_scale_only_rows_fit_one_factor_per_mode():
    """--scale-only zeroes the per-target features: the model is the intercept and the two
    cross-fitted mode factors, the ratio of the modes' variances kept."""
    rows = _rows(6, per_mode=300)
    rows[:, 6:] = 0.0
    model = cross_fit(rows, position_groups(rows, 0))
    np.testing.assert_array_equal(model[1:6], 0.0)
    ratio = (model[6] / model[7]) / (
        np.quantile(rows[rows[:, 3] == 1, 4], 0.95) / np.quantile(rows[rows[:, 3] == 0, 4], 0.95)
    )
    assert ratio == pytest.approx(1.0, rel=0.25)
