"""The IMM (track/imm.py) against a plain numpy IMM (tests/track/naive.py), and inside the
tracker's step: a track's state is the textbook IMM's; a static target is averaged."""

import numpy as np
import pytest

from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.track import imm
from spiel_edge.track.layout import allocate, model_views, state_views
from spiel_edge.track.step import step_kernel
from tests.track import naive

ACC, Q2, V02 = 1000.0, 4.0, 300.0**2


def _models(rng):
    xm = np.stack([rng.normal(0, 50, 6) for _ in range(2)])
    pm = np.stack([(a @ a.T + np.eye(6)) for a in rng.normal(0, 5, (2, 6, 6))])
    mu = rng.dirichlet([1.0, 1.0])
    return xm, pm, mu


@pytest.mark.parametrize("dt,switch", [(0.0, 0.3), (0.02, 0.05), (0.5, 0.5), (0.02, 0.0)])
def test_mix_predict_matches_numpy(rng, dt, switch):
    for _ in range(10):
        xm, pm, mu = _models(rng)
        got = imm.mix_predict(xm, pm, mu, dt, ACC, Q2, switch, V02)
        want = naive.imm_mix_predict(xm, pm, mu, dt, ACC, Q2, switch, V02)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-8)
        assert np.array_equal(got[4], got[4].T)


def test_update_matches_numpy(rng):
    for _ in range(20):
        xm, pm, mu = _models(rng)
        a = rng.normal(0, 10, (3, 3))
        z, r = rng.normal(0, 50, 3), a @ a.T + np.eye(3)
        got = imm.update(xm, pm, mu, z, r)
        want = naive.imm_update(xm, pm, mu, z, r)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-8, atol=1e-8)
        assert got[2].sum() == pytest.approx(1.0)
        assert np.array_equal(got[4], got[4].T)


def test_update_rejects_a_singular_innovation():
    xm, pm, mu = np.zeros((2, 6)), np.zeros((2, 6, 6)), np.array([0.5, 0.5])
    assert imm.update(xm, pm, mu, np.ones(3), np.zeros((3, 3))) is None


def test_far_measurement_does_not_underflow_the_weights():
    """Likelihoods of exp(-1e4) each: the weights stay finite and sum to 1."""
    xm = np.zeros((2, 6))
    pm = np.stack([np.eye(6), 4.0 * np.eye(6)])
    got = imm.update(xm, pm, np.array([0.5, 0.5]), np.full(3, 300.0), np.eye(3))
    assert np.all(np.isfinite(got[2])) and got[2].sum() == pytest.approx(1.0)
    assert got[2][1] > 0.99  # the wider model explains it far better


def _params(spec: TrackSpec) -> np.ndarray:
    return np.array(
        [spec.acceleration_mm_s2, spec.gate_chi2, spec.measurement_floor_mm**2,
         spec.fallback_sigma_mm**2, spec.initial_speed_mm_s**2, spec.confirm_hits,
         spec.confirm_window, spec.max_misses, spec.imm_static_noise_mm**2,
         spec.imm_switch_probability, spec.imm_static_share]
    )  # fmt: skip


def test_step_runs_the_textbook_imm_per_track(rng):
    """Two far apart targets, every acquisition seen: each slot's models, weights and estimate
    are those of the numpy IMM run on that target's measurements."""
    spec = TrackSpec(imm_switch_probability=0.05)  # persistent models: each target picks one
    params = _params(spec)
    arrays = allocate(4, params)
    truth = np.array([[-100.0, 0.0, 200.0], [100.0, 0.0, 200.0]])
    velocity = np.array([[0.0, 0.0, 0.0], [300.0, -200.0, 100.0]])
    floor2 = params[2]
    reference = [None, None]
    for k in range(40):
        truth = truth + velocity * 0.02
        z = truth + rng.normal(0, 5, (2, 3))
        r = np.stack([np.diag(rng.uniform(16, 100, 3)) for _ in range(2)])
        step_kernel(*arrays, z, r, 0.02 if k else 0.0)
        rf = r + floor2 * np.eye(3)
        for t in range(2):
            if reference[t] is None:  # birth: both models on the target
                p0 = np.zeros((6, 6))
                p0[:3, :3], p0[3:, 3:] = rf[t], params[4] * np.eye(3)
                xm = np.stack([np.r_[z[t], 0, 0, 0]] * 2)
                mu = np.array([spec.imm_static_share, 1 - spec.imm_static_share])
                reference[t] = (xm, np.stack([p0, p0]), mu)
                continue
            xm, pm, mu, _, _ = naive.imm_mix_predict(
                *reference[t], 0.02, params[0], params[8], params[9], params[4]
            )
            reference[t] = naive.imm_update(xm, pm, mu, z[t], rf[t])[:3]
    x, p, _, _ = state_views(*arrays[:2])
    xm_got, pm_got, mu_got = model_views(arrays[0], 4)
    for t in range(2):
        s = int(np.argmin(np.linalg.norm(x[:, :3] - truth[t], axis=1)))
        np.testing.assert_allclose(xm_got[s], reference[t][0], rtol=1e-7, atol=1e-6)
        np.testing.assert_allclose(pm_got[s], reference[t][1], rtol=1e-7, atol=1e-6)
        np.testing.assert_allclose(mu_got[s], reference[t][2], rtol=1e-7, atol=1e-9)
        want_x, want_p = naive.imm_combine(*reference[t])
        np.testing.assert_allclose(x[s], want_x, rtol=1e-7, atol=1e-6)
        np.testing.assert_allclose(p[s], want_p, rtol=1e-7, atol=1e-6)
    # the still target is held by the static model, the moving one by the CV model
    s_still = int(np.argmin(np.linalg.norm(x[:, :3] - truth[0], axis=1)))
    s_moving = int(np.argmin(np.linalg.norm(x[:, :3] - truth[1], axis=1)))
    assert mu_got[s_still, 0] > 0.8 and mu_got[s_moving, 1] > 0.8
