import dataclasses

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages.associate import GeometricAssociator, anchor_triples
from spiel_edge.pipeline.stages.echo_quality import echo_quality
from spiel_edge.pipeline.stages.features import N_FEATURES, TOA_COLUMN
from spiel_edge.pipeline.stages.locate import locate, locate_kernel, solve3
from spiel_edge.pipeline.stages.memg import solve_spd
from spiel_edge.sim.synthetic import ring_profile
from tests.core import naive


def geometry(profile):
    g = profile.geometry
    return g.channels_mm, g.emitter_mm, g.facing


@pytest.mark.parametrize("target", [(0, 0, 100), (40, -80, 180), (-80, 80, 220), (120, 30, 60)])
def test_locate_exact_on_every_channel_subset(profile, target):
    ch, e, f = geometry(profile)
    target = np.array(target, float)
    d = naive.paths(target, ch, e)
    for use in ([1, 1, 1, 1], [0, 1, 1, 1], [1, 0, 1, 1], [1, 1, 0, 1], [1, 1, 1, 0]):
        pos, rms, ok = locate(d, ch, e, f, np.array(use, bool))
        assert ok and rms < 1e-6
        np.testing.assert_allclose(pos, target, atol=1e-5)


def test_locate_matches_scipy_least_squares_with_noise(profile, rng):
    ch, e, f = geometry(profile)
    for _ in range(30):
        target = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), rng.uniform(80, 300)])
        d = naive.paths(target, ch, e) + rng.normal(0, 4, 4)
        use = np.ones(4, bool)
        pos, rms, ok = locate(d, ch, e, f, use)
        ref, ref_rms = naive.locate(d, ch, e, use, pos + rng.normal(0, 1, 3))
        assert ok
        np.testing.assert_allclose(pos, ref, atol=1e-3)
        assert rms == pytest.approx(ref_rms, abs=1e-6)


def test_weighted_locate_matches_scipy_and_trusts_the_heavier_channels(profile, rng):
    ch, e, f = geometry(profile)
    target = np.array([30.0, -40.0, 160.0])
    d = naive.paths(target, ch, e)
    d[1] += 25.0  # one corrupted channel
    weights = np.array([1.0, 0.05, 1.0, 1.0])
    use = np.ones(4, bool)
    pos, rms, ok = locate(d, ch, e, f, use, weights=weights)
    ref, ref_rms = naive.locate(d, ch, e, use, pos + 1.0, weights)
    assert ok
    np.testing.assert_allclose(pos, ref, atol=1e-3)
    assert rms == pytest.approx(ref_rms, abs=1e-5)  # the reported rms is the plain one
    plain, _, _ = locate(d, ch, e, f, use)
    assert np.linalg.norm(pos - target) < 0.5 * np.linalg.norm(plain - target)
    with pytest.raises(InputError, match="weights"):
        locate(d, ch, e, f, use, weights=np.array([1.0, 0.0, 1.0, 1.0]))


def test_echo_quality_weights_and_shifts(profile):
    spec = dataclasses.replace(
        profile.locate,
        toa_sigma_samples=0.3,
        toa_sigma_per_background=0.5,
        toa_sigma_alpha_counts=8.0,
        toa_shift_background_after=-0.8,
        toa_shift_background_before=0.2,
    )
    frames = np.full((4, 64), 100.0)
    background = np.zeros((4, 64))
    background[1, 22] = 100.0  # after channel 1's echo, as strong as the frame: ratio 1
    background[2, 18] = 50.0  # before channel 2's echo: ratio 0.5
    toa = np.array([20.0, 20.0, 20.0, np.nan])
    alpha = np.array([400.0, 400.0, 400.0, np.nan])
    weights, shift = echo_quality(frames, background, toa, alpha, spec)
    strength = 8.0 / 400
    np.testing.assert_allclose(weights[:3], 1 / (0.3 + np.array([0.0, 0.5, 0.25]) + strength))
    np.testing.assert_allclose(
        shift, [0.0, 0.8, -0.1, 0.0]
    )  # early echoes move later, late ones earlier
    assert weights[3] == pytest.approx(1 / 0.3)  # no echo: untouched (and unused)
    weights, shift = echo_quality(frames, None, toa, alpha, spec)
    np.testing.assert_allclose(weights[:3], 1 / (0.3 + strength))
    assert not shift.any()
    with pytest.raises(InputError, match="background shape"):
        echo_quality(frames, background[:, :32], toa, alpha, spec)


def test_locate_never_nan_and_keeps_target_in_front(profile, rng):
    ch, e, f = geometry(profile)
    for d in (
        np.full(4, np.nan),
        np.zeros(4),
        np.array([1e9, 1, 1, 1]),
        rng.normal(0, 500, 4),
        np.array([10.0, 500, 3, 80]),
    ):
        pos, rms, ok = locate(d, ch, e, f)
        assert np.all(np.isfinite(pos))
        if ok:
            assert pos @ f > 0
    pos, rms, ok = locate(np.array([200.0, 200.0, np.nan, np.nan]), ch, e, f)
    assert not ok and np.all(pos == 0)  # fewer than 3 channels


def _bits(values):
    return np.asarray(values, dtype=np.float64).tobytes()


def test_solve3_is_solve_spd_bit_for_bit(rng):
    for trial in range(3000):
        m = rng.normal(0, 10 ** rng.uniform(-6, 4), (3, 3))
        a = m @ m.T + (0.0 if trial % 3 == 0 else rng.uniform(0, 1e-3)) * np.eye(3)
        if trial % 7 == 0:
            a = -a  # not positive definite
        b = rng.normal(0, 100, 3)
        ok, x = naive.cholesky_solve(a, b)
        ref = np.empty(3)
        assert solve_spd(a.copy(), b, 3, ref) == ok
        got = solve3(a[0, 0], a[1, 0], a[1, 1], a[2, 0], a[2, 1], a[2, 2], *b)
        assert got[0] == ok
        if ok:
            assert _bits(got[1:]) == _bits(x) == _bits(ref)


@pytest.mark.parametrize("n_channels", [4, 6, 8])
def test_locate_kernel_is_the_array_reference_bit_for_bit(profile, n_channels, rng):
    """The scalar solve (no arrays, |p - e| once per point) against the plain-Python copy of
    the array version it replaced: the same position, rms and flag, bit for bit."""
    if n_channels == 4:
        ch, e, f = geometry(profile)
    else:
        ch, e, f = geometry(ring_profile(n_channels, 256))
    n_ok = 0
    for trial in range(400):
        target = rng.normal(0, 120, 3)
        target[2] = abs(target[2]) + 20 if trial % 5 else -abs(target[2])  # some behind
        d = naive.paths(target, ch, e) + rng.normal(0, 10 ** rng.uniform(-3, 1.5), len(ch))
        use = rng.random(len(ch)) < 0.8
        use[:3] = trial % 11 != 0 or use[:3]  # mostly >= 3 channels
        w = np.ones(len(ch)) if trial % 2 else rng.uniform(0.1, 3.0, len(ch))
        if trial % 17 == 0:
            d = rng.normal(0, 500, len(ch))  # nonsense paths
        out = np.empty(3)
        ok, rms = locate_kernel(d, use, w, e, ch, f, 20 + trial % 11, out)
        ok_ref, rms_ref, pos_ref = naive.locate_lm(d, use, w, e, ch, f, 20 + trial % 11)
        assert ok == ok_ref
        assert _bits([rms]) == _bits([rms_ref])
        assert _bits(out) == _bits(pos_ref)
        n_ok += ok
    assert n_ok > 200


def _features_from_paths(profile, paths_by_channel, alpha=500.0):
    """Feature arrays whose ToA column puts echoes at the given path lengths."""
    n_ch = len(paths_by_channel)
    k = max(len(p) for p in paths_by_channel)
    feats = np.full((n_ch, k, N_FEATURES), np.nan)
    counts = np.zeros(n_ch, dtype=np.int64)
    delays = profile.geometry.delays()
    for c, ps in enumerate(paths_by_channel):
        for i, p in enumerate(sorted(ps)):
            feats[c, i, TOA_COLUMN] = p / profile.mm_per_sample + delays[c]
            feats[c, i, 0] = alpha
        counts[c] = len(ps)
    return feats, counts


def test_geometric_association_picks_the_target_among_clutter(profile, rng):
    ch, e, _ = geometry(profile)
    assoc = GeometricAssociator(profile)
    for _ in range(20):
        target = np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(100, 200)])
        true_paths = naive.paths(target, ch, e)
        echoes = [[tp + rng.normal(0, 1.0)] + list(rng.uniform(400, 900, 2)) for tp in true_paths]
        feats, counts = _features_from_paths(profile, echoes)
        matched = assoc(feats, counts)
        toa = feats[np.arange(4), matched, TOA_COLUMN]
        picked = (toa - profile.geometry.delays()) * profile.mm_per_sample
        np.testing.assert_allclose(picked, true_paths, atol=4.0)


def test_geometric_association_drops_a_blind_channel(profile):
    ch, e, _ = geometry(profile)
    true_paths = naive.paths(np.array([20.0, -30.0, 150.0]), ch, e)
    echoes = [[true_paths[0]], [], [true_paths[2], 700.0], [true_paths[3]]]
    feats, counts = _features_from_paths(profile, echoes)
    matched = GeometricAssociator(profile)(feats, counts)
    assert matched.tolist() == [0, -1, 0, 0]


def test_exhaustive_search_matches_brute_force(profile, rng):
    ch, e, f = geometry(profile)
    assoc = GeometricAssociator(profile)
    weights = (
        assoc.max_residual_mm,
        assoc.missing_penalty_mm,
        assoc.strength_weight_mm,
        assoc.range_weight,
    )
    for _ in range(25):
        targets = [
            np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(100, 250)])
            for _ in range(2)
        ]
        echoes = [
            [naive.paths(t, ch, e)[c] + rng.normal(0, 3) for t in targets if rng.random() < 0.85]
            + list(rng.uniform(300, 900, rng.integers(0, 2)))
            for c in range(4)
        ]
        feats, counts = _features_from_paths(profile, echoes)
        feats[:, :, 0] = rng.uniform(50, 1000, feats.shape[:2])
        matched, cost = assoc.candidates(feats, counts)
        paths = assoc.paths_mm(feats)
        strength = np.log(np.where(feats[:, :, 0] > 1, feats[:, :, 0], 1))
        want, want_cost = naive.brute_force_association(
            paths,
            counts,
            ch,
            e,
            f,
            weights,
            strength,
            assoc.min_channels,
            assoc.max_path_diff,
            locate,
        )
        if want is None:
            assert np.isinf(cost)
        else:
            assert cost == pytest.approx(want_cost, abs=1e-6)
            assert matched.tolist() == list(want)


@pytest.mark.parametrize("n_channels", [8, 16])
def test_hypothesis_search_on_large_arrays(n_channels, rng):
    profile = ring_profile(n_channels, 512)
    ch, e, _ = geometry(profile)
    assoc = GeometricAssociator(profile)
    assert assoc.anchors is not None and len(assoc.anchors) >= 2
    for _ in range(10):
        target = np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(100, 250)])
        echoes = [
            [naive.paths(target, ch, e)[c] + rng.normal(0, 1), rng.uniform(620, 900)]
            for c in range(n_channels)
        ]
        echoes[0] = echoes[0][1:]  # an anchor misses the target: the other triples must find it
        feats, counts = _features_from_paths(profile, echoes)
        matched = assoc(feats, counts)
        picked = (
            feats[np.arange(n_channels), matched, TOA_COLUMN] - profile.geometry.delays()
        ) * profile.mm_per_sample
        ok = matched >= 0
        assert ok.sum() >= n_channels - 1
        np.testing.assert_allclose(picked[ok], naive.paths(target, ch, e)[ok], atol=4.0)


def test_anchor_triples_are_disjoint_and_spread():
    profile = ring_profile(10, 256)
    g = profile.geometry
    triples = anchor_triples(g.channels_mm, g.emitter_mm, np.arange(10))
    assert triples.shape == (3, 3)
    assert len(set(triples.ravel().tolist())) == 9
    assert triples[0, 0] == 0  # the channel at the emitter
