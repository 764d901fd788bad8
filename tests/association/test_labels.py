"""Ground-truth echo labels and association scores."""

from __future__ import annotations

import numpy as np

from spiel_edge.measure.echo_labels import (
    AssociationScore,
    expected_toa,
    label_echoes,
    score_association,
)
from spiel_edge.pipeline.stages.features import N_FEATURES, TOA_COLUMN


def _features(toas: list[list[float]]) -> tuple[np.ndarray, np.ndarray]:
    k = max(len(t) for t in toas)
    f = np.full((len(toas), k, N_FEATURES), np.nan)
    for c, t in enumerate(toas):
        f[c, : len(t), TOA_COLUMN] = t
    return f, np.array([len(t) for t in toas])


def test_expected_toa_is_path_over_sample_length_plus_delay(profile):
    truth = np.array([0.0, 0.0, 150.0])
    t = expected_toa(profile, truth)
    g = profile.geometry
    assert np.isclose(t[0], 300.0 / profile.mm_per_sample + g.delays()[0])
    path2 = 150.0 + np.hypot(75.0, 150.0)
    assert np.isclose(t[2], path2 / profile.mm_per_sample + g.delays()[2])


def test_label_is_the_nearest_echo_within_tolerance():
    f, counts = _features([[10.0, 20.0, 30.0], [19.0, 21.4], [25.0], []])
    labels = label_echoes(f, counts, np.array([20.6, 20.6, 20.6, 20.6]), tolerance=1.5)
    assert labels.tolist() == [1, 1, -1, -1]


def test_score_counts_hits_misses_and_empty_channels():
    sc = score_association(np.array([1, 0, -1, 2]), np.array([1, 1, -1, -1]))
    assert (sc.correct, sc.channels, sc.tp, sc.fp, sc.fn) == (2, 4, 1, 2, 1)
    assert np.isclose(sc.f1, 2 / 5)
    total = sc + score_association(np.array([0, 0, 0, 0]), np.array([0, 0, 0, 0]))
    assert total.channels == 8 and total.correct == 6 and np.isclose(total.accuracy, 0.75)
    assert np.isnan(AssociationScore().accuracy)


def test_listening_mask_drops_channels():
    sc = score_association(
        np.array([1, 0, 0]), np.array([1, 1, 0]), listening=np.array([True, False, True])
    )
    assert sc.channels == 2 and sc.correct == 2
