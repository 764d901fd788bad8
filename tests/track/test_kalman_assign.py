"""The tracker's kernels against plain numpy references."""

import numpy as np
import pytest

from spiel_edge.track import kalman
from spiel_edge.track.assign import INFEASIBLE, assign
from tests.track import naive


def _random_state(rng):
    a = rng.normal(size=(6, 6))
    return rng.normal(0, 100, 6), a @ a.T + np.eye(6)


def _random_cov(rng, scale=10.0):
    a = rng.normal(0, scale, (3, 3))
    return a @ a.T + np.eye(3)


@pytest.mark.parametrize("dt", [0.0, 0.02, 0.5])
def test_predict_matches_numpy(rng, dt):
    x, p = _random_state(rng)
    got_x, got_p = kalman.predict(x, p, dt, 2500.0)
    want_x, want_p = naive.kf_predict(x, p, dt, 2500.0)
    np.testing.assert_allclose(got_x, want_x, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(got_p, want_p, rtol=1e-10, atol=1e-8)


def test_update_and_gate_match_numpy(rng):
    for _ in range(20):
        x, p = _random_state(rng)
        z, r = rng.normal(0, 100, 3), _random_cov(rng)
        got_x, got_p = kalman.update(x, p, z, r)
        want_x, want_p = naive.kf_update(x, p, z, r)
        np.testing.assert_allclose(got_x, want_x, rtol=1e-9, atol=1e-8)
        np.testing.assert_allclose(got_p, want_p, rtol=1e-9, atol=1e-8)
        assert np.array_equal(got_p, got_p.T)
        assert kalman.mahalanobis2(x, p, z, r) == pytest.approx(naive.mahalanobis2(x, p, z, r))


def test_singular_innovation_leaves_the_state():
    x, p = np.ones(6), np.zeros((6, 6))
    got_x, got_p = kalman.update(x, p, np.zeros(3), np.zeros((3, 3)))
    assert np.array_equal(got_x, x) and np.array_equal(got_p, p)
    assert kalman.mahalanobis2(x, p, np.zeros(3), np.zeros((3, 3))) == np.inf


def test_assignment_matches_brute_force(rng):
    for _ in range(150):
        n, m = rng.integers(0, 5, 2)
        cost = rng.normal(0, 5, (n, m))
        feasible = rng.random((n, m)) < 0.6
        got = assign(np.where(feasible, cost, INFEASIBLE))
        pairs = [(i, j) for i, j in enumerate(got) if j >= 0]
        assert len({j for _, j in pairs}) == len(pairs)  # one row per column
        assert all(feasible[i, j] for i, j in pairs)
        want_pairs, want_cost = naive.best_matching(cost, feasible)
        assert len(pairs) == want_pairs
        assert sum(cost[i, j] for i, j in pairs) == pytest.approx(want_cost, abs=1e-9)


def test_assignment_takes_non_finite_as_infeasible():
    cost = np.array([[np.nan, 1.0], [np.inf, -np.inf]])
    assert assign(cost).tolist() == [1, -1]
    with pytest.raises(ValueError, match="2-D"):
        assign(np.zeros(3))
