"""The echo-recall helpers (tools/research/echo_recall_steps.py) on hand-made cases."""

import numpy as np
import pytest

from spiel_edge.errors import InputError
from tools.research.echo_recall_steps import (
    gap_bin,
    ideal_toa,
    nearest_echo,
    shared_echo,
    truth_gap,
)


def test_ideal_toa_adds_delay_and_offset():
    paths = np.array([[156.0, 312.0]])
    out = ideal_toa(paths, 15.6, np.array([1.0, 2.0]), offset=np.array([0.5, -0.5]))
    np.testing.assert_allclose(out, [[11.5, 21.5]])
    with pytest.raises(InputError):
        ideal_toa(paths, 15.6, np.array([1.0]))
    with pytest.raises(InputError):
        ideal_toa(paths, 0.0, np.array([1.0, 2.0]))


def test_nearest_echo_is_signed_and_nan_without_echoes():
    toa = np.array([[10.0, 20.0, np.nan], [np.nan, np.nan, np.nan]])
    ideal = np.array([[19.2, 5.0], [11.0, 5.0]])
    d = nearest_echo(toa, ideal)
    np.testing.assert_allclose(d[:, 0], [0.8, -1.0])
    assert np.isnan(d[:, 1]).all()
    with pytest.raises(InputError):
        nearest_echo(toa, np.zeros((1, 3)))


def test_truth_gap_and_bins():
    ideal = np.array([[10.0, 30.0], [12.5, 30.5], [20.0, 40.0]])
    np.testing.assert_allclose(truth_gap(ideal), [[2.5, 0.5], [2.5, 0.5], [7.5, 9.5]])
    assert np.isinf(truth_gap(ideal[:1])).all()
    np.testing.assert_array_equal(
        gap_bin(np.array([0.5, 1.0, 2.5, 3.0, np.inf]), (1.0, 2.0, 3.0)), [0, 1, 2, 3, 3]
    )


def test_shared_echo_only_when_both_truths_pick_the_same_echo():
    toa = np.array([[10.0, 14.0]])
    near = shared_echo(toa, np.array([[9.6], [10.5]]), 1.0)
    assert near.all()
    apart = shared_echo(toa, np.array([[9.6], [13.8]]), 1.0)
    assert not apart.any()
    too_far = shared_echo(toa, np.array([[9.6], [11.5]]), 1.0)  # second truth has no echo
    assert not too_far.any()
