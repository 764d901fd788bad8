import numpy as np
import pytest
from scipy.optimize import curve_fit

from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages.detect import detect
from spiel_edge.pipeline.stages.features import FEATURE_NAMES, echo_features
from spiel_edge.pipeline.stages.memg import (
    emg_value,
    fit_memg,
    jacobian_sums,
    solve_spd,
    trial_cost,
)
from tests.core import naive

T = np.arange(64.0)


def test_emg_value_and_jacobian_match_numpy():
    params = (700.0, 20.3, 1.7, 1.4)
    row = np.empty(4)
    for t in (15.0, 20.0, 22.5, 30.0):
        value = naive.emg_jacobian_row(t, *params, row, 0)
        assert value == pytest.approx(naive.emg(t, *params), rel=1e-12)
        assert emg_value(t, *params) == pytest.approx(value, rel=1e-12)
        for i in range(4):
            h = 1e-6 * max(1.0, abs(params[i]))
            up, down = list(params), list(params)
            up[i] += h
            down[i] -= h
            numeric = (naive.emg(t, *up) - naive.emg(t, *down)) / (2 * h)
            assert row[i] == pytest.approx(numeric, rel=1e-5, abs=1e-6)


def test_normal_equations_match_numpy(rng):
    p = np.array([700.0, 20.3, 1.7, 1.4, 300.0, 24.0, 2.0, -0.5])
    y = rng.uniform(0, 900, 64)
    a, b = np.empty((8, 8)), np.empty(8)
    cost = naive.normal_equations(y, 14, 31, p, 2, np.empty(8), a, b)
    t = np.arange(14.0, 31.0)
    r = y[14:31] - naive.emg(t, *p[:4]) - naive.emg(t, *p[4:])
    jac = np.empty((t.size, 8))
    for i, ti in enumerate(t):
        naive.emg_jacobian_row(ti, *p[:4], jac[i], 0)
        naive.emg_jacobian_row(ti, *p[4:], jac[i], 4)
    assert cost == pytest.approx(float(r @ r), rel=1e-12)
    np.testing.assert_allclose(a, jac.T @ jac, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(b, jac.T @ r, rtol=1e-10, atol=1e-9)


def test_trial_cost_and_jacobian_sums_are_the_normal_equations_bit_for_bit(rng):
    """The fit's two passes (the one-component sums in registers) against the one-pass loop."""
    y = rng.uniform(0, 900, 64)
    for p in (
        [700.0, 20.3, 1.7, 1.4],
        [50.0, 30.0, 0.4, -4.0],
        [900.0, 12.2, 6.0, 8.0],
        [700.0, 20.3, 1.7, 1.4, 300.0, 24.0, 2.0, -0.5],
    ):
        p = np.array(p)
        n_comp, n_par = len(p) // 4, len(p)
        a, b = np.empty((n_par, n_par)), np.empty(n_par)
        want = naive.normal_equations(y, 14, 31, p, n_comp, np.empty(n_par), a, b)
        shape, resid = np.empty(3 * n_comp * 17), np.empty(17)
        a2, b2 = np.full((n_par, n_par), np.nan), np.full(n_par, np.nan)
        assert trial_cost(y, 14, 31, p, n_comp, shape, resid, np.inf) == want
        partial = trial_cost(y, 14, 31, p, n_comp, np.empty_like(shape), resid.copy(), 1.0)
        assert 1.0 <= partial <= want  # stopped early: the step would be rejected anyway
        jacobian_sums(17, p, n_comp, shape, resid, np.empty(n_par), a2, b2)
        assert np.array_equal(a, a2) and np.array_equal(b, b2)


def test_solve_spd_matches_numpy(rng):
    for n in (1, 3, 8, 16):
        m = rng.normal(size=(n, n))
        a = m @ m.T + n * np.eye(n)
        b = rng.normal(size=n)
        x = np.empty(n)
        assert solve_spd(a.copy(), b, n, x)
        np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-9)
    assert not solve_spd(-np.eye(3), np.ones(3), 3, np.empty(3))


def _fit(y):
    peaks, counts = detect(y, threshold=20, min_amplitude=30, max_echoes=4)
    return fit_memg(y, peaks, counts, mu_window=3.0, max_iterations=60), peaks, counts


def test_memg_recovers_single_echo_like_scipy(rng):
    truth = (900.0, 24.4, 1.8, 1.2)
    y = naive.emg(T, *truth)[None, :] + rng.normal(0, 2, (1, 64))
    params, _, counts = _fit(np.clip(y, 0, None))
    assert counts[0] == 1
    ref, _ = curve_fit(naive.emg, T, y[0], p0=[500, 24, 1.5, 1.0])
    np.testing.assert_allclose(params[0, 0], ref, rtol=0.02, atol=0.05)
    np.testing.assert_allclose(params[0, 0], truth, rtol=0.03, atol=0.06)


def test_memg_separates_overlapping_echoes():
    y = (naive.emg(T, 800, 20.0, 1.5, 1.0) + naive.emg(T, 500, 25.5, 1.5, 1.0))[None, :]
    params, _, counts = _fit(y)
    assert counts[0] == 2
    np.testing.assert_allclose(params[0, :2, 1], [20.0, 25.5], atol=0.1)
    np.testing.assert_allclose(params[0, :2, 0], [800, 500], rtol=0.05)


def test_memg_respects_bounds_and_validates():
    y = np.zeros((1, 64))
    y[0, 30] = 1000  # a spike no EMG can fit well
    params, _, _ = _fit(y)
    alpha, mu, sigma, _ = params[0, 0]
    assert alpha > 0 and 0.4 <= sigma <= 6.0 and abs(mu - 30) <= 3.0
    with pytest.raises(InputError, match="ascending"):
        fit_memg(y, np.array([[5, 3]]), np.array([2]))  # not ascending
    with pytest.raises(InputError, match="ascending"):
        fit_memg(y, np.array([[5, 64]]), np.array([2]))  # outside the frame
    with pytest.raises(InputError, match="counts"):
        fit_memg(y, np.array([[5, 9]]), np.array([3]))
    fit_memg(y, np.array([[5, -1]]), np.array([1]))  # padding after the count is ignored


def test_features_match_numpy_reference():
    p = (900.0, 24.4, 1.8, 1.2)
    y = naive.emg(T, *p)[None, :] + naive.emg(T, 300.0, 45.0, 2.0, 0.5)[None, :]
    params = np.full((1, 2, 4), np.nan)
    params[0, 0], params[0, 1] = p, (300.0, 45.0, 2.0, 0.5)
    peaks = np.array([[25, 45]])
    dense = np.linspace(10, 40, 300001)
    curve = naive.emg(dense, *p)
    mode = dense[np.argmax(curve)]
    half = dense[np.argmax(curve >= curve.max() / 2)]
    for toa, want in (("mode", mode), ("mu", 24.4), ("half", half)):
        f = echo_features(y, params, peaks, toa)
        assert f[0, 0, FEATURE_NAMES.index("toa")] == pytest.approx(want, abs=1e-4)
    f = echo_features(y, params, peaks, "mode")
    assert f[0, 0, FEATURE_NAMES.index("power")] == pytest.approx(naive.emg(T, *p).sum(), rel=1e-6)
    assert f[0, 0, FEATURE_NAMES.index("frame_confidence")] == pytest.approx(
        1.0, abs=1e-9
    )  # perfect model
    assert f[0, 0, FEATURE_NAMES.index("echo_confidence")] == pytest.approx(1.0, abs=1e-9)
    # the data peak estimator: parabola through the 3 samples around the detected peak
    yy = y[0]
    k = 25 if yy[25] >= yy[24] else 24
    f = echo_features(y, params, np.array([[k, 45]]), "peak")
    den = yy[k - 1] - 2 * yy[k] + yy[k + 1]
    assert f[0, 0, 6] == pytest.approx(k + 0.5 * (yy[k - 1] - yy[k + 1]) / den)


def test_mode_is_the_maximum_for_every_bounded_eta():
    from spiel_edge.pipeline.stages.features import component_mode

    for eta in np.linspace(-4.0, 8.0, 49):
        t = np.linspace(18.0, 25.0, 700001)  # mu 20, sigma 1: [mu - 2 sigma, mu + 5 sigma]
        want = t[np.argmax(naive.emg(t, 500.0, 20.0, 1.0, eta))]
        assert component_mode(500.0, 20.0, 1.0, eta) == pytest.approx(want, abs=2e-5)


def test_features_of_a_channel_do_not_depend_on_the_others(rng):
    """Channels run LANES at a time in the kernel; each one's features must be the bits it
    gets alone (the single-channel path), for every channel count."""
    for n_ch in (1, 3, 4, 5, 8, 9):
        y = rng.uniform(0, 50, (n_ch, 64))
        params = np.full((n_ch, 3, 4), np.nan)
        peaks = np.full((n_ch, 3), -1)
        for c in range(n_ch):
            for k in range(c % 4):
                mu = 10.0 + 17.0 * k + rng.uniform(0, 5)
                params[c, k] = (rng.uniform(100, 900), mu, rng.uniform(0.4, 6), rng.uniform(-4, 8))
                peaks[c, k] = int(mu)
                y[c] += naive.emg(T, *params[c, k])
        whole = echo_features(y, params, peaks)
        for c in range(n_ch):
            alone = echo_features(y[c : c + 1], params[c : c + 1], peaks[c : c + 1])
            assert np.array_equal(whole[c], alone[0], equal_nan=True)
