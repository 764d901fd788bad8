"""The echo-timing step: numba kernels against numpy references, edges, the pipeline with it."""

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.stages.echo_timing import (
    EchoTiming,
    clean_envelope,
    n_toa_features,
    refine_toa,
    timing_delays,
    toa_features,
)
from tests.core import naive


def _frames(rng, n_ch=4, n_t=64):
    f = rng.uniform(0, 50, (n_ch, n_t))
    b = rng.uniform(0, 60, (n_ch, n_t))
    t = np.arange(n_t)
    for c in range(n_ch):
        f[c] += 900 * np.exp(-0.5 * ((t - 20.3 - 3 * c) / 1.4) ** 2)
    return f, b


@pytest.mark.parametrize("with_background", [True, False])
def test_kernels_match_numpy_references(rng, with_background):
    f, b = _frames(rng)
    b = b if with_background else None
    clean = clean_envelope(f, b, 9)
    np.testing.assert_allclose(clean, naive.clean_envelope(f, b, 9))
    toa = np.array([20.0, 23.4, np.nan, 29.6])
    for estimator, log_domain in (("parabola", False), ("log_parabola", True)):
        got = refine_toa(clean, toa, 2, estimator)
        np.testing.assert_allclose(got, naive.refine_toa(clean, toa, 2, log_domain), equal_nan=True)
    refined = refine_toa(clean, toa, 2)
    feats = toa_features(f, b, clean, refined)
    assert feats.shape == (4, n_toa_features(4))
    np.testing.assert_allclose(feats, naive.toa_features(f, b, clean, refined), equal_nan=True)


def test_log_parabola_finds_a_gaussian_peak_exactly():
    t = np.arange(64.0)
    clean = np.array([1000 * np.exp(-0.5 * ((t - mu) / 1.5) ** 2) for mu in (20.3, 31.75, 40.0)])
    got = refine_toa(clean, np.array([21.0, 31.0, 39.0]), 2, "log_parabola")
    np.testing.assert_allclose(got, [20.3, 31.75, 40.0], atol=1e-9)


def test_echo_at_the_frame_edge_keeps_its_toa_and_gets_nan_features():
    clean = np.zeros((4, 64))
    clean[0, 63] = 500.0  # peak on the last sample: no parabola
    clean[1, 1:4] = [100.0, 300.0, 100.0]  # window of the features would leave the frame
    toa = np.array([62.8, 2.0, np.nan, 10.0])  # channel 3: all zeros, no peak
    refined = refine_toa(clean, toa, 2)
    assert refined[0] == 62.8 and refined[1] == pytest.approx(2.0) and refined[3] == 10.0
    assert np.isnan(refined[2])
    feats = toa_features(clean, None, clean, refined)
    assert np.isnan(feats[[0, 1, 2]]).all(axis=1).all() and np.isfinite(feats[3]).all()


def test_bad_input_is_a_clear_error():
    with pytest.raises(InputError, match="background shape"):
        clean_envelope(np.zeros((4, 64)), np.zeros((4, 32)))
    with pytest.raises(InputError, match="one value per channel"):
        refine_toa(np.zeros((4, 64)), np.zeros(3))
    with pytest.raises(InputError, match="estimator"):
        EchoTiming("spline")


def test_step_without_correction_only_refines(rng):
    f, b = _frames(rng)
    toa = np.array([20.0, 23.0, 26.0, np.nan])
    out = EchoTiming("log_parabola", 2, 9)(f, b, toa)
    assert np.isnan(out[3]) and np.all(np.abs(out[:3] - toa[:3]) <= 2.5)
    assert EchoTiming("none")(f, b, toa) is not None


def test_profile_turns_the_step_and_its_delays_on(profile):
    assert profile.echo_timing.estimator != "none"
    shift = np.asarray(profile.echo_timing.delay_shift_samples)
    np.testing.assert_allclose(timing_delays(profile), profile.geometry.delays() + shift)


@pytest.mark.parametrize("choice", ["auto", "none"])
def test_pipeline_fixes_every_subset_frame_with_and_without_background(profile, subset, choice):
    pipe = build_pipeline(profile, "geometric", choice)
    assert pipe.echo_timing.active and (pipe.echo_timing.correction is None) == (choice == "none")
    for i in range(0, len(subset), 25):
        for bg in (subset.backgrounds[i], None):
            r = pipe.process(subset.frames[i], bg, timed=True)
            assert r.position_mm is None or np.all(np.isfinite(r.position_mm))
            assert "echo_timing" in r.timings_us


@pytest.mark.parametrize(
    "change, message",
    [
        ({"estimator": "spline"}, "echo_timing.estimator"),
        ({"toa_correction": "maybe"}, "echo_timing.toa_correction"),
        ({"delay_shift_samples": [0.1, 0.2]}, "delay_shift_samples"),
        ({"delay_shift_samples": ["a", 1, 2, 3]}, "list of numbers"),
        ({"half_window": 0}, "half_window"),
    ],
)
def test_profile_echo_timing_section_is_validated(profile, change, message):
    from spiel_edge.errors import ConfigError
    from spiel_edge.profile.schema import profile_from_dict, profile_to_dict

    data = profile_to_dict(profile)
    assert data["echo_timing"]["toa_correction"] == "auto"
    data["echo_timing"].update(change)
    with pytest.raises(ConfigError, match=message):
        profile_from_dict(data)
