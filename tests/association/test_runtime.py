"""OnnxAssociator on the vendored recordings: interface, accuracy, no torch at run time."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.measure.echo_labels import AssociationScore, score_association
from spiel_edge.pipeline.learned.associate_onnx import (
    OnnxAssociator,
    bench_scoring,
    candidate_mask,
    guarded_match,
    score_bonus,
)
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.pipeline.stages.features import FEATURE_NAMES


@pytest.fixture(scope="module")
def assoc(profile):
    return OnnxAssociator(profile)


def test_matched_indices_are_valid(assoc, subset_features):
    for features, counts, _, _ in subset_features:
        matched = assoc(features, counts)
        assert matched.dtype == np.int64 and matched.shape == counts.shape
        assert np.all((matched >= -1) & (matched < np.maximum(counts, 0)))
        assert (matched >= 0).sum() in (0, 3, 4)  # a combination needs >= 3 channels


def test_scores_every_echo_in_one_call(assoc, subset_features):
    features, counts, _, _ = subset_features[0]
    rows, score, embedding = assoc.score(features, counts)
    assert len(rows[0]) == counts.sum() == len(score) == len(embedding)
    assert embedding.shape[1] == 4 and np.all((score >= 0) & (score <= 1))


def _accuracy(matches, subset_features) -> AssociationScore:
    total = AssociationScore()
    for m, (_, _, labels, _) in zip(matches, subset_features, strict=True):
        total = total + score_association(m, labels)
    return total


def test_accuracy_beats_the_strongest_echo_baseline(assoc, subset_features):
    alpha = FEATURE_NAMES.index("alpha")
    learned = _accuracy([assoc(f, c) for f, c, _, _ in subset_features], subset_features)
    strongest = _accuracy(
        [
            np.where(c > 0, np.nanargmax(np.nan_to_num(f[:, :, alpha], nan=-1.0), axis=1), -1)
            for f, c, _, _ in subset_features
        ],
        subset_features,
    )
    geometric = _accuracy([g for _, _, _, g in subset_features], subset_features)
    assert learned.accuracy >= strongest.accuracy + 0.05
    assert learned.accuracy >= 0.9
    assert learned.accuracy >= geometric.accuracy - 0.03  # the guard keeps it near geometry


def test_reference_is_always_a_candidate():
    rows = (np.array([0, 1, 2]), np.array([0, 0, 1]))
    emb = np.array([[0.0, 0, 0, 0], [5.0, 0, 0, 0], [0.5, 0, 0, 0]])
    allowed = candidate_mask((3, 2), rows, np.array([0.2, 0.1, 0.9]), emb, threshold=1.0)
    assert allowed.tolist() == [[True, False], [False, False], [False, True]]


def test_guard_falls_back_to_the_unrestricted_search(profile, subset_features):
    geo = GeometricAssociator(profile)
    features, counts, _, expected = next(s for s in subset_features if (s[3] >= 0).sum() >= 3)
    nothing = np.zeros(features.shape[:2], dtype=bool)
    assert guarded_match(geo, features, counts, nothing).tolist() == expected.tolist()
    assert guarded_match(geo, features, counts, nothing, slack_mm=0.0).tolist() == expected.tolist()
    everything = np.ones(features.shape[:2], dtype=bool)
    assert (
        guarded_match(geo, features, counts, everything, slack_mm=math.inf).tolist()
        == expected.tolist()
    )


def test_runtime_never_imports_torch():
    code = textwrap.dedent("""
        import sys
        from spiel_edge.data import load_subset
        from spiel_edge.pipeline.factory import build_pipeline
        from spiel_edge.profile.schema import load_profile
        pipe = build_pipeline(load_profile("spiel-icra23"), "onnx")
        assert type(pipe.associator).__name__ == "OnnxAssociator", pipe.associator
        d = load_subset()
        r = pipe.process(d.frames[0], d.backgrounds[0])
        assert r.position_mm is not None
        print("torch" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_bench_scoring_reports_timings(profile):
    out = bench_scoring(n=50, profile=profile)
    assert out["n"] == 50 and out["scoring_us"]["median"] > 0
    assert out["associate_us"]["median"] >= out["scoring_us"]["median"] * 0.5


def test_prior_weight_zero_is_the_geometric_associator(profile, subset_features):
    zero = OnnxAssociator(profile, score_weight_mm=0.0)
    for features, counts, _, geometric in subset_features:
        assert zero(features, counts).tolist() == geometric.tolist()


def test_score_bonus_is_the_weighted_logit():
    rows = (np.array([0, 2]), np.array([1, 0]))
    bonus = score_bonus((3, 2), rows, np.array([0.5, 0.9], dtype=np.float32), 2.0)
    assert bonus[0, 1] == pytest.approx(0.0) and bonus[2, 0] == pytest.approx(2.0 * math.log(9.0))
    assert np.count_nonzero(bonus) == 1


def test_the_prior_decides_between_consistent_combinations(profile):
    """Two targets, both seen on every channel: the echoes the net scores high win."""
    geo = GeometricAssociator(profile)
    g = profile.geometry
    near, far = np.array([10.0, 20.0, 120.0]), np.array([-30.0, 10.0, 170.0])
    features = np.full((4, 2, len(FEATURE_NAMES)), np.nan)
    for k, target in enumerate((near, far)):
        path = np.linalg.norm(target - g.emitter_mm) + np.linalg.norm(
            target - g.channels_mm, axis=1
        )
        features[:, k, FEATURE_NAMES.index("toa")] = path / profile.mm_per_sample + g.delays()
        features[:, k, FEATURE_NAMES.index("alpha")] = 300.0
    counts = np.full(4, 2)
    assert geo(features, counts).tolist() == [0, 0, 0, 0]  # geometry alone: the near one
    rows = (np.repeat(np.arange(4), 2), np.tile([0, 1], 4))
    favour_far = score_bonus((4, 2), rows, np.tile([0.05, 0.95], 4).astype(np.float32), 4.0)
    assert geo.candidates(features, counts, bonus_mm=favour_far)[0].tolist() == [1, 1, 1, 1]


def test_reference_mode_and_bad_mode(profile, subset_features):
    reference = OnnxAssociator(profile, mode="reference")
    features, counts, _, _ = subset_features[0]
    matched = reference(features, counts)
    assert np.all((matched >= -1) & (matched < np.maximum(counts, 0)))
    with pytest.raises(InputError, match="mode"):
        OnnxAssociator(profile, mode="best")
