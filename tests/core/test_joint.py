"""Joint choice of the targets (pipeline/stages/joint.py): the combination pool and the subset search
against brute-force numpy references, bounded cost in clutter, K = 1 unchanged."""

import dataclasses

import numpy as np
import pytest

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.pipeline.stages.joint import MAX_NODES, combination_pool, select_subset
from spiel_edge.pipeline.stages.locate import locate
from spiel_edge.profile.schema import profile_from_dict, profile_to_dict
from spiel_edge.sim.synthetic import synthesize
from tests.core import naive
from tests.core.test_locate_associate import _features_from_paths, geometry


def with_scene(profile, **kw):
    return profile.replace(scene=dataclasses.replace(profile.scene, **kw))


def _objective(choices, gains, chosen, share):
    uses = {}
    for i in chosen:
        for c, k in enumerate(choices[i]):
            if k >= 0:
                uses[(c, k)] = uses.get((c, k), 0) + 1
    return sum(gains[i] for i in chosen) - share * sum(u - 1 for u in uses.values())


def _random_case(rng, m):
    choices = rng.integers(-1, 3, (m, 4))
    choices[:, 0] = np.maximum(choices[:, 0], 0)  # at least one echo each
    gains = np.sort(rng.normal(5.0, 8.0, m))[::-1]
    return choices, gains


def test_subset_search_matches_brute_force(rng):
    for _ in range(150):
        m = int(rng.integers(1, 10))
        choices, gains = _random_case(rng, m)
        k = int(rng.integers(1, 5))
        share = float(rng.choice([0.0, 2.0, 6.0, 40.0]))
        chosen = select_subset(choices, gains, k, share)
        want = naive.joint_selection_value(choices, gains, k, share)
        assert len(chosen) <= k and len(set(chosen.tolist())) == len(chosen)
        assert _objective(choices, gains, chosen, share) == pytest.approx(want, abs=1e-9)


def test_subset_search_exclusivity_and_ghosts():
    # 0 = a ghost made of echoes of 1 and 2 (cheapest), 1 and 2 two targets, 3 = 1 again
    choices = np.array([[0, 0, 1, 1], [0, 0, 0, 0], [1, 1, 1, 1], [0, 0, 0, -1]])
    gains = np.array([12.0, 10.0, 9.0, 8.0])
    assert select_subset(choices, gains, 4, 6.0).tolist() == [1, 2]
    assert select_subset(choices, gains, 1, 6.0).tolist() == [0]
    # with no cost for sharing, the ghost still never joins both targets it is made of
    assert select_subset(choices, gains, 4, 0.0).tolist() == [0, 1]
    assert select_subset(choices, -np.abs(gains)[::-1], 4, 6.0).size == 0


def test_subset_search_bad_input():
    choices = np.zeros((2, 4), dtype=np.int64)
    for gains in (np.array([1.0, 2.0]), np.array([np.nan, 1.0]), np.array([1.0])):
        with pytest.raises(InputError):
            select_subset(choices, gains, 2, 1.0)
    with pytest.raises(InputError):
        select_subset(choices, np.array([2.0, 1.0]), 0, 1.0)


def test_subset_search_bounded_with_many_candidates(rng):
    """Hundreds of candidates, K = 16: stops at the node budget with a valid, non-empty set
    at least as good as the best single combination."""
    choices = rng.integers(-1, 16, (400, 4))
    choices[:, 0] = np.maximum(choices[:, 0], 0)
    gains = np.sort(rng.uniform(0.1, 50.0, 400))[::-1]
    chosen = select_subset(choices, gains, 16, 1.0, max_nodes=MAX_NODES)
    assert 1 <= len(chosen) <= 16
    assert _objective(choices, gains, chosen, 1.0) >= gains[0]
    tiny = select_subset(choices, gains, 16, 1.0, max_nodes=1)
    assert len(tiny) <= 1


def test_pool_matches_brute_force_and_associator(profile, rng):
    ch, e, f = geometry(profile)
    assoc = GeometricAssociator(profile)
    weights = (
        assoc.max_residual_mm,
        assoc.missing_penalty_mm,
        assoc.strength_weight_mm,
        assoc.range_weight,
    )
    for _ in range(15):
        targets = [
            np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(100, 250)])
            for _ in range(2)
        ]
        echoes = [
            [naive.paths(t, ch, e)[c] + rng.normal(0, 3) for t in targets if rng.random() < 0.9]
            + list(rng.uniform(300, 900, rng.integers(0, 2)))
            for c in range(4)
        ]
        feats, counts = _features_from_paths(profile, echoes)
        feats[:, :, 0] = rng.uniform(50, 1000, feats.shape[:2])
        choices, costs = combination_pool(assoc, feats, counts, max_pool=4096)
        want = naive.brute_force_costs(
            assoc.paths_mm(feats),
            counts,
            ch,
            e,
            f,
            weights,
            np.log(np.where(feats[:, :, 0] > 1, feats[:, :, 0], 1)),
            assoc.min_channels,
            assoc.max_path_diff,
            locate,
        )
        assert sorted(map(tuple, choices.tolist())) == sorted(want)
        for choice, cost in zip(choices, costs, strict=True):
            # ill-conditioned combinations: the kernel and numpy solves stop a little apart
            assert cost == pytest.approx(want[tuple(choice)], abs=0.1)
        assert np.all(np.diff(costs) >= 0)
        if len(costs):
            matched, best = assoc.candidates(feats, counts)
            assert choices[0].tolist() == matched.tolist() and costs[0] == best
        few, few_costs = combination_pool(assoc, feats, counts, max_pool=3)
        assert np.array_equal(few_costs, costs[:3])


def test_joint_two_targets_and_k1_unchanged(profile):
    targets = np.array([[0.0, 0.0, 120.0], [60.0, 40.0, 250.0]])
    frames, background = synthesize(profile, targets, seed=3)
    single = Pipeline(profile).process(frames, background)
    greedy = Pipeline(with_scene(profile, selection="greedy")).process(frames, background)
    assert single.record() == greedy.record()  # K = 1 never reaches the selection
    multi = Pipeline(with_scene(profile, max_targets=4, selection="joint"))
    found = np.array([t.position_mm for t in multi.process(frames, background).targets])
    for truth in targets:
        assert np.linalg.norm(found - truth, axis=1).min() < 15.0


def test_joint_bounded_with_hundreds_of_echo_candidates(profile, rng):
    prof = with_scene(profile, max_targets=16, max_cost_mm=1000.0, selection="joint")
    prof = prof.replace(detect=dataclasses.replace(prof.detect, max_echoes=16, threshold=1.0))
    pipe = Pipeline(prof)
    for _ in range(3):
        result = pipe.process(rng.uniform(0, 3000, (4, 64)), None)
        assert len(result.targets) <= 16
        for t in result.targets:
            assert np.all(np.isfinite(t.position_mm)) and np.all(np.isfinite(t.covariance_mm2))


def test_selection_key_checked(profile):
    data = profile_to_dict(profile)
    bad = {**data, "scene": {**data["scene"], "selection": "best"}}
    with pytest.raises(ConfigError, match="scene.selection"):
        profile_from_dict(bad)


def test_no_background_covariance_scale(profile, subset):
    frames, background = subset.frames[0], subset.backgrounds[0]
    base = with_scene(profile, covariance_floor_mm=0.0, covariance_scale_no_background=1.0)
    wide = with_scene(base, covariance_scale_no_background=2.0)
    a, b = Pipeline(base).process(frames, None), Pipeline(wide).process(frames, None)
    np.testing.assert_allclose(b.targets[0].covariance_mm2, 4.0 * a.targets[0].covariance_mm2)
    a, b = Pipeline(base).process(frames, background), Pipeline(wide).process(frames, background)
    np.testing.assert_array_equal(b.targets[0].covariance_mm2, a.targets[0].covariance_mm2)
    data = profile_to_dict(profile)
    bad = {**data, "scene": {**data["scene"], "covariance_scale_no_background": 0.0}}
    with pytest.raises(ConfigError, match="scene.covariance_scale_no_background"):
        profile_from_dict(bad)
