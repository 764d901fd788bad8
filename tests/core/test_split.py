"""The merged-echo split (pipeline/stages/split.py): two echoes 2-4 samples apart that detect reports
as one are found as two; one echo is not split; max_echoes holds; a numpy reference agrees."""

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.measure.reference import fit_memg as reference_fit_memg
from spiel_edge.pipeline.stages.detect import detect
from spiel_edge.pipeline.stages.features import TOA_COLUMN, echo_features
from spiel_edge.pipeline.stages.memg import WINDOW_AFTER, WINDOW_BEFORE, fit_memg
from spiel_edge.pipeline.stages.split import MIN_SHARE, SPLIT_OFFSET, split_merged
from tests.core import naive

T = np.arange(96.0)
SHAPE = (2.0, 1.0)  # sigma, eta: about this board's single echo (median sigma 2.07 samples)
SPLIT = {"min_sigma": 2.0, "max_cost_ratio": 0.6}


def _front(y, max_echoes=6, **split):
    peaks, counts = detect(y, threshold=20, min_amplitude=30, max_echoes=max_echoes)
    params = fit_memg(y, peaks, counts, max_iterations=30)
    return (peaks, counts, params), split_merged(y, peaks, counts, params, **(split or SPLIT))


def _modes(y, peaks, params):
    return echo_features(y, params, peaks)[:, :, TOA_COLUMN]


@pytest.mark.parametrize("gap", [2, 3, 4])
def test_two_echoes_detected_as_one_are_split(gap, rng):
    first, second = naive.emg(T, 700, 40.0, *SHAPE), naive.emg(T, 500, 40.0 + gap, *SHAPE)
    y = np.clip(first + second + rng.normal(0, 2, T.size), 0, None)[None, :]
    (_, counts, _), (peaks2, counts2, params2) = _front(y)
    assert counts[0] == 1  # detect and MEMG alone see one echo
    assert counts2[0] == 2
    true_modes = [T[first.argmax()], T[second.argmax()]]
    np.testing.assert_allclose(_modes(y, peaks2, params2)[0, :2], true_modes, atol=0.75)
    assert peaks2[0, 0] < peaks2[0, 1]


def test_one_echo_is_not_split(rng):
    for seed in range(5):
        noise = np.random.default_rng(seed).normal(0, 3, T.size)
        y = np.clip(naive.emg(T, 700, 40.0, *SHAPE) + noise, 0, None)[None, :]
        before, after = _front(y)
        assert after[1][0] == before[1][0] == 1
        np.testing.assert_array_equal(after[2], before[2])


def test_max_echoes_is_respected():
    merged = naive.emg(T, 700, 20.0, *SHAPE) + naive.emg(T, 500, 23.0, *SHAPE)
    other = naive.emg(T, 600, 60.0, *SHAPE)
    y = (merged + other)[None, :]
    (_, counts, _), (_, full_counts, _) = _front(y, max_echoes=2)
    assert counts[0] == full_counts[0] == 2  # no free slot: nothing split
    (_, counts, _), (peaks, counts3, params) = _front(y, max_echoes=3)
    assert counts[0] == 2 and counts3[0] == 3
    assert (np.diff(peaks[0, :3]) > 0).all()


def test_kernel_matches_numpy_reference(rng):
    """The split is MEMG's two-component fit at detection -/+ SPLIT_OFFSET, kept when it
    leaves <= max_cost_ratio of the one-component residual over that window."""
    for gap in (2.5, 3.5):
        y = naive.emg(T, 700, 40.0, *SHAPE) + naive.emg(T, 450, 40.0 + gap, *SHAPE)
        y = np.clip(y + rng.normal(0, 2, T.size), 0, None)[None, :]
        (peaks, counts, params), (_, counts2, params2) = _front(y)
        assert counts[0] == 1
        pk = int(peaks[0, 0])
        starts = np.array([[pk - SPLIT_OFFSET, pk + SPLIT_OFFSET]])
        two = reference_fit_memg(y, starts, np.array([2]), mu_window=3.0, max_iter=30)[0]
        lo, hi = pk - SPLIT_OFFSET - WINDOW_BEFORE, pk + SPLIT_OFFSET + WINDOW_AFTER + 1
        t = T[lo:hi]
        cost1 = np.sum((y[0, lo:hi] - naive.emg(t, *params[0, 0])) ** 2)
        cost2 = np.sum((y[0, lo:hi] - naive.emg(t, *two[0]) - naive.emg(t, *two[1])) ** 2)
        keep = (
            cost2 <= SPLIT["max_cost_ratio"] * cost1
            and two[:, 0].min() >= MIN_SHARE * two[:, 0].max()
        )
        assert keep and counts2[0] == 2
        ref_modes = [naive.emg(T, *p).argmax() for p in two]
        np.testing.assert_allclose(params2[0, :2, 1], two[:, 1], atol=0.15)
        np.testing.assert_allclose(
            [T[naive.emg(T, *p).argmax()] for p in params2[0, :2]], ref_modes, atol=1
        )


def test_split_validates_and_does_not_modify_inputs():
    y = (naive.emg(T, 700, 20.0, *SHAPE) + naive.emg(T, 500, 23.0, *SHAPE))[None, :]
    peaks, counts = detect(y, threshold=20, min_amplitude=30, max_echoes=4)
    params = fit_memg(y, peaks, counts)
    copies = peaks.copy(), counts.copy(), params.copy()
    split_merged(y, peaks, counts, params, **SPLIT)
    for a, b in zip((peaks, counts, params), copies, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(InputError, match="max_cost_ratio"):
        split_merged(y, peaks, counts, params, min_sigma=2.0, max_cost_ratio=1.5)
    with pytest.raises(InputError, match="counts"):
        split_merged(y, peaks, np.array([9]), params, **SPLIT)
    with pytest.raises(InputError, match="params"):
        split_merged(y, peaks, counts, params[:, :, :3], **SPLIT)
