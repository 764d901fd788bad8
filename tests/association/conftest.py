"""Shared fixtures: the vendored recordings through the stages (no /work/shared, no torch)."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.data import load_subset
from spiel_edge.measure.echo_labels import expected_toa, label_echoes
from spiel_edge.pipeline import Pipeline
from spiel_edge.profile.schema import load_profile


@pytest.fixture(scope="session")
def profile():
    return load_profile("spiel-icra23")


@pytest.fixture(scope="session")
def subset_features(profile):
    """(features, counts, labels, geometric matched) per vendored acquisition, z = 90 mm excluded."""
    data = load_subset()
    pipe = Pipeline(profile)
    out = []
    for frames, bg, truth in zip(data.frames, data.backgrounds, data.truth_mm, strict=True):
        if truth[2] == 90.0:
            continue
        r = pipe.process(frames, bg)
        labels = label_echoes(r.features, r.counts, expected_toa(profile, truth))
        geo = np.array([-1 if m is None else m for m in r.matched], dtype=np.int64)
        out.append((r.features, r.counts, labels, geo))
    return out
