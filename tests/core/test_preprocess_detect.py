import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages.detect import detect
from spiel_edge.pipeline.stages.preprocess import envelope, preprocess
from tests.core import naive

frames_st = arrays(
    np.float64,
    st.tuples(st.integers(1, 6), st.integers(8, 80)),
    elements=st.floats(0, 5000, allow_nan=False, width=32),
)


@settings(max_examples=60, deadline=None)
@given(frames_st, st.integers(0, 8), st.booleans())
def test_preprocess_matches_numpy(frames, blind, with_bg):
    bg = np.flip(frames, axis=1).copy() if with_bg else None
    blind = min(blind, frames.shape[1])
    got = preprocess(frames, bg, blind_zone=blind)
    np.testing.assert_allclose(got, naive.preprocess(frames, bg, blind))


def test_preprocess_rejects_bad_input():
    with pytest.raises(InputError, match="NaN"):
        preprocess(np.array([[1.0, np.nan, 3.0]]))
    with pytest.raises(InputError, match="shape"):
        preprocess(np.ones((4, 64)), np.ones((4, 32)))
    with pytest.raises(InputError, match="2-D"):
        preprocess(np.ones(64))


def test_envelope_matches_numpy_and_recovers_pulse(rng):
    f = 0.2  # carrier cycles per sample
    t = np.arange(200)
    pulse = 1000 * np.exp(-0.5 * ((t - 90) / 12.0) ** 2)
    rf = np.vstack([pulse * np.cos(2 * np.pi * f * t + phase) for phase in (0.0, 1.0, 2.5)])
    rf += rng.normal(0, 1, rf.shape)
    got = envelope(rf, f)
    np.testing.assert_allclose(got, naive.envelope(rf, f), atol=1e-9)
    # phase-invariant: every channel's envelope peaks at the pulse centre with its amplitude
    assert np.all(np.abs(np.argmax(got, axis=1) - 90) <= 1)
    np.testing.assert_allclose(got.max(axis=1), 1000, rtol=0.05)


@settings(max_examples=80, deadline=None)
@given(
    frames_st,
    st.floats(5, 500),
    st.floats(0, 1),
    st.floats(0, 1000),
    st.integers(1, 6),
    st.integers(0, 10),
)
def test_detect_matches_numpy(y, threshold, hysteresis, min_amp, k, first):
    got = detect(
        y,
        threshold=threshold,
        hysteresis=hysteresis,
        min_amplitude=min_amp,
        max_echoes=k,
        first_sample=first,
    )
    want = naive.detect(y, threshold, hysteresis, min_amp, k, first)
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_array_equal(got[0], want[0])


@settings(max_examples=120, deadline=None)
@given(
    arrays(
        np.float64,
        st.tuples(st.integers(1, 4), st.integers(2, 40)),
        elements=st.sampled_from([0.0, 10.0, 40.0, 80.0]),
    ),
    st.integers(1, 3),
    st.integers(0, 4),
)
def test_detect_matches_numpy_with_ties(y, k, first):
    """Few levels: equal maxima, rises at the first and last samples, echoes of one sample
    (the one-pass kernel tracks each echo's maximum as it goes)."""
    got = detect(
        y, threshold=20.0, hysteresis=0.5, min_amplitude=10.0, max_echoes=k, first_sample=first
    )
    want = naive.detect(y, 20.0, 0.5, 10.0, k, first)
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_array_equal(got[0], want[0])


def test_detect_finds_separate_echoes_and_keeps_strongest():
    t = np.arange(64.0)
    y = np.vstack(
        [
            800 * np.exp(-0.5 * ((t - 20) / 1.5) ** 2) + 300 * np.exp(-0.5 * ((t - 40) / 1.5) ** 2),
            np.zeros(64),
        ]
    )
    peaks, counts = detect(y, threshold=30, max_echoes=4)
    assert counts.tolist() == [2, 0]
    assert peaks[0, :2].tolist() == [20, 40]
    peaks, counts = detect(y, threshold=30, max_echoes=1)
    assert peaks[0, 0] == 20 and counts[0] == 1
