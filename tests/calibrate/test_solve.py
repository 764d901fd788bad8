"""The solver on synthetic echo times from a known perturbed geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from spiel_edge.calibrate import Observations, predict_toa, solve
from spiel_edge.errors import InputError
from tests.calibrate.synth import echo_times, nominal, perturbed_truth, target_grid

FS = 22000.0


def _scene(seed: int, m: int = 1000, noise: float = 0.15, outliers: float = 0.05):
    rng = np.random.default_rng(seed)
    start = dataclasses.replace(nominal().geometry, delay_samples=np.zeros(4))
    truth = perturbed_truth(start, rng)
    targets, ch, toa, bad = echo_times(truth, target_grid(rng, m), FS, rng, noise, outliers)
    return start, truth, Observations(targets, ch, toa), bad


@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_perturbed_geometry_within_targets(seed):
    start, truth, obs, bad = _scene(seed)
    res = solve(obs, start, FS)
    g = res.geometry
    assert np.max(np.abs(g.channels_mm - truth.channels_mm)) < 1.0
    assert np.max(np.abs(g.emitter_mm - truth.emitter_mm)) < 1.0
    assert abs(g.speed_of_sound_m_s / truth.speed_of_sound_m_s - 1) < 0.005
    assert np.max(np.abs(g.delays() - truth.delays())) < 0.05
    # the wrong echoes (>= 2 samples off at 0.15 noise) are exactly the rejected ones
    assert np.array_equal(res.rejected, bad)
    assert 0.1 < res.scale < 0.2


def test_reported_uncertainty_matches_the_scatter():
    errors, stds = [], []
    for seed in range(12):
        start, truth, obs, _ = _scene(100 + seed, m=300, outliers=0.0)
        res = solve(obs, start, FS)
        values = dict(zip(res.names, res.values, strict=True))
        errors.append(
            [
                values["r2.x"] - truth.channels_mm[2, 0],
                values["c"] - truth.speed_of_sound_m_s,
                values["d1"] - truth.delays()[1],
            ]
        )
        stds.append([res.std[res.names.index(n)] for n in ("r2.x", "c", "d1")])
    z = np.array(errors) / np.array(stds)
    ratio = np.sqrt(np.mean(z**2, axis=0))  # ~1 when the 1-sigma is right
    assert np.all((ratio > 0.5) & (ratio < 1.6)), ratio


def test_fixed_parameters_keep_their_start_values():
    start, truth, obs, _ = _scene(2, m=300)
    res = solve(obs, start, FS, fix={"emitter", "speed", "receivers_z"})
    g = res.geometry
    assert g.speed_of_sound_m_s == start.speed_of_sound_m_s
    assert np.array_equal(g.emitter_mm, start.emitter_mm)
    assert np.array_equal(g.channels_mm[:, 2], start.channels_mm[:, 2])
    assert not any(n.startswith("e.") or n == "c" or n.endswith(".z") for n in res.names)
    assert np.any(g.channels_mm[:, :2] != start.channels_mm[:, :2])


def test_fixed_receivers_move_rigidly_with_the_emitter():
    rng = np.random.default_rng(5)
    start = nominal().geometry
    shift = np.array([2.0, -1.0, 3.0])
    truth = dataclasses.replace(
        start, emitter_mm=start.emitter_mm + shift, channels_mm=start.channels_mm + shift
    )
    targets, ch, toa, _ = echo_times(truth, target_grid(rng, 200), FS, rng, 0.05, 0.0)
    res = solve(Observations(targets, ch, toa), start, FS, fix={"receivers", "delays", "speed"})
    assert np.allclose(res.geometry.channels_mm, truth.channels_mm, atol=0.2)


def test_noise_free_residuals_vanish():
    start, truth, obs, _ = _scene(3, m=100, noise=0.0, outliers=0.0)
    res = solve(obs, start, FS)
    assert np.max(np.abs(res.residuals)) < 1e-6
    assert np.allclose(
        predict_toa(res.geometry, obs.targets_mm, obs.channels, FS), obs.toa, atol=1e-6
    )


def test_one_target_position_cannot_determine_the_geometry():
    start = nominal().geometry
    targets = np.repeat([[10.0, 20.0, 150.0]], 40, axis=0)
    ch = np.tile(np.arange(4), 10)
    toa = predict_toa(start, targets, ch, FS)
    with pytest.raises(InputError, match="cannot separate"):
        solve(Observations(targets, ch, toa), start, FS)


@pytest.mark.parametrize(
    "bad, message",
    [
        (dict(toa=np.array([np.nan, 1.0])), "finite"),
        (dict(channels=np.array([0, 7])), "channels must be in"),
        (dict(targets_mm=np.zeros((2, 2))), "targets_mm"),
    ],
)
def test_bad_observations_are_rejected_clearly(bad, message):
    obs = dict(
        targets_mm=np.array([[0.0, 0, 100], [0, 0, 150]]),
        channels=np.array([0, 1]),
        toa=np.array([10.0, 12.0]),
    )
    obs.update(bad)
    with pytest.raises(InputError, match=message):
        solve(Observations(**obs), nominal().geometry, FS)


def test_too_few_observations_and_unknown_fix():
    obs = Observations(np.array([[0.0, 0, 100]]), np.array([0]), np.array([10.0]))
    with pytest.raises(InputError, match="cannot determine"):
        solve(obs, nominal().geometry, FS)
    with pytest.raises(InputError, match="fixable"):
        solve(obs, nominal().geometry, FS, fix={"antenna"})
