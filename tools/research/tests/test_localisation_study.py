"""The localisation study's helpers (tools/research/localisation_fits.py) on synthetic data."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.profile.schema import load_profile
from tools.research.localisation_fits import (
    bias_and_noise,
    fit_delays_and_scale,
    path_jacobian,
    position_folds,
    position_sd_mm,
)

GEOMETRY = load_profile("spiel-icra23").geometry


def test_folds_keep_every_height_of_a_position_together():
    xys = [(x, y, z) for x in (-40, 0, 40) for y in (0, 80) for z in (100, 180, 220)]
    folds = position_folds(xys, 3)
    by_xy: dict = {}
    for (x, y, _), f in zip(xys, folds, strict=True):
        by_xy.setdefault((x, y), set()).add(int(f))
    assert all(len(s) == 1 for s in by_xy.values())
    assert set(folds.tolist()) == {0, 1, 2}
    assert (position_folds(xys[::-1], 3)[::-1] == folds).all()  # order of rows does not matter
    with pytest.raises(InputError):
        position_folds(xys, 1)


def test_bias_and_noise_separates_pose_bias_from_frame_noise():
    rng = np.random.default_rng(0)
    groups = np.repeat(np.arange(200), 20)
    bias = rng.normal(0, 0.4, (200, 4))[groups]
    noise = rng.normal(0, 0.25, (groups.size, 4))
    r = bias + noise
    r[::7, 1] = np.nan  # missing echoes are skipped
    total, between, within = bias_and_noise(r, groups)
    assert between == pytest.approx(0.4, abs=0.03)
    assert within == pytest.approx(0.25, abs=0.01)
    assert total == pytest.approx(np.hypot(0.4, 0.25), abs=0.03)
    with pytest.raises(InputError):
        bias_and_noise(r[:, 0], groups)
    with pytest.raises(InputError):
        bias_and_noise(r, groups[:-1])


def test_path_jacobian_matches_finite_differences():
    p = np.array([30.0, -50.0, 180.0])
    j = path_jacobian(p, GEOMETRY.channels_mm, GEOMETRY.emitter_mm)
    h = 1e-4
    fd = np.stack(
        [
            (GEOMETRY.echo_paths_mm(p + h * e) - GEOMETRY.echo_paths_mm(p - h * e)) / (2 * h)
            for e in np.eye(3)
        ],
        axis=1,
    )
    np.testing.assert_allclose(j, fd, atol=1e-6)


def test_position_sd_grows_with_range_and_path_error():
    near = position_sd_mm(np.array([0, 0, 100.0]), GEOMETRY.channels_mm, GEOMETRY.emitter_mm, 5.0)
    far = position_sd_mm(np.array([0, 0, 220.0]), GEOMETRY.channels_mm, GEOMETRY.emitter_mm, 5.0)
    assert near[0] == pytest.approx(near[1], rel=1e-3)  # symmetric array, target on its axis
    assert far[0] > 1.7 * near[0]  # lateral error grows with range ...
    assert far[2] < far[0] / 5  # ... while range stays well determined
    double = position_sd_mm(np.array([0, 0, 220.0]), GEOMETRY.channels_mm, GEOMETRY.emitter_mm, 10)
    np.testing.assert_allclose(double, 2 * far)


def test_position_sd_matches_monte_carlo_of_the_linearised_solve():
    rng = np.random.default_rng(1)
    p = np.array([80.0, 0.0, 180.0])
    j = path_jacobian(p, GEOMETRY.channels_mm, GEOMETRY.emitter_mm)
    noise = rng.normal(0, 5.0, (20000, 4))
    est = noise @ np.linalg.pinv(j).T
    np.testing.assert_allclose(
        est.std(0),
        position_sd_mm(p, GEOMETRY.channels_mm, GEOMETRY.emitter_mm, 5.0),
        rtol=0.03,
    )


def test_fit_delays_and_scale_recovers_both():
    rng = np.random.default_rng(2)
    ideal = rng.uniform(10, 30, (300, 4))
    delays = np.array([2.1, 1.6, 1.9, 1.7])
    toa = delays + 1.017 * ideal + rng.normal(0, 0.05, ideal.shape)
    toa[5, 2] = np.nan
    inlier = np.ones(toa.shape, bool)
    inlier[7, 1] = False
    toa[7, 1] += 20  # an outlier left out by the caller's mask
    d, k = fit_delays_and_scale(toa, ideal, inlier, scale=True)
    assert k == pytest.approx(1.017, abs=0.002)
    np.testing.assert_allclose(d, delays, atol=0.05)
    d0, k0 = fit_delays_and_scale(toa, ideal, inlier, scale=False)
    assert k0 == 1.0
    np.testing.assert_allclose(d0, delays + 0.017 * 20, atol=0.1)  # the scale folded in
    with pytest.raises(InputError):
        fit_delays_and_scale(toa, ideal, np.zeros(toa.shape, bool), scale=True)
    with pytest.raises(InputError):
        fit_delays_and_scale(toa[:, :3], ideal, inlier, scale=True)
