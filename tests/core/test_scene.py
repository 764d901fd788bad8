"""Scene stage: several targets, shared echoes, double reflections, covariance, static model."""

import dataclasses

import numpy as np
import pytest

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.scene import is_double_reflection, predicted_paths, shared_echoes
from spiel_edge.pipeline.stages.static_scene import load_static_model
from spiel_edge.pipeline.stages.uncertainty import CHI2_95_3DOF, mahalanobis2, position_covariance
from spiel_edge.profile.schema import profile_from_dict, profile_to_dict
from spiel_edge.sim.synthetic import synthesize
from tests.core import naive


def with_scene(profile, **kw):
    return profile.replace(scene=dataclasses.replace(profile.scene, **kw))


def geometry(profile):
    g = profile.geometry
    return np.asarray(g.channels_mm, float), np.asarray(g.emitter_mm, float)


@pytest.mark.parametrize("use", [[1, 1, 1, 1], [1, 0, 1, 1], [0, 1, 1, 1]])
def test_covariance_kernel_matches_numpy_reference(profile, rng, use):
    ch, e = geometry(profile)
    use = np.array(use, bool)
    for _ in range(10):
        p = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), rng.uniform(60, 300)])
        d = naive.paths(p, ch, e) + rng.normal(0, 3, 4)
        sigma = rng.uniform(2, 10, 4)
        got = position_covariance(p, d, sigma, use, ch, e, scale=1.3, floor_mm=4.0)
        ref = naive.position_covariance(p, d, sigma, use, ch, e, 1.3, 4.0)
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-6)
        assert np.array_equal(got, got.T) and np.linalg.eigvalsh(got).min() > 0


def test_covariance_always_finite_symmetric_positive(profile):
    ch, e = geometry(profile)
    cases = [
        (np.array([0.0, 0.0, 100.0]), np.zeros(4, bool)),  # no channel at all: the prior
        (np.array([np.nan, 0.0, 100.0]), np.ones(4, bool)),  # NaN position
        (np.array([0.0, 0.0, 0.0]), np.ones(4, bool)),  # on the emitter itself
    ]
    for p, use in cases:
        d = np.full(4, 200.0)
        c = position_covariance(p, d, np.full(4, 5.0), use, ch, e)
        assert np.all(np.isfinite(c)) and np.array_equal(c, c.T)
        assert np.linalg.eigvalsh(c).min() > 0
    with pytest.raises(InputError):
        position_covariance(np.zeros(3), np.zeros(4), np.ones(4), np.ones(4, bool), ch, e, -1.0)


def test_covariance_covers_simulated_toa_noise(profile, rng):
    """With the true path error, small enough for the linearisation to hold, the 95 %
    ellipsoid holds the truth about 95 % of the time (larger errors are the floor's job)."""
    from spiel_edge.pipeline.stages.locate import locate

    ch, e = geometry(profile)
    f = np.asarray(profile.geometry.facing, float)
    sigma = np.array([0.4, 0.6, 0.5, 0.8])
    inside = []
    for _ in range(400):
        truth = np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(100, 220)])
        d = naive.paths(truth, ch, e) + rng.normal(0, sigma)
        use = np.array([True, True, True, False])  # 3 channels: no residual inflation
        pos, _, ok = locate(d, ch, e, f, use, weights=1 / sigma)
        cov = position_covariance(pos, d, sigma, use, ch, e)
        inside.append(ok and mahalanobis2(pos - truth, cov) <= CHI2_95_3DOF)
    assert 0.9 <= np.mean(inside) <= 0.99


def test_two_targets_found_and_best_first_unchanged(profile):
    targets = np.array([[0.0, 0.0, 120.0], [60.0, 40.0, 250.0]])
    frames, background = synthesize(profile, targets, seed=3)
    single = Pipeline(profile).process(frames, background)
    multi = Pipeline(with_scene(profile, max_targets=4)).process(frames, background)
    assert len(single.targets) == 1
    np.testing.assert_allclose(single.targets[0].position_mm, single.position_mm)
    np.testing.assert_allclose(multi.position_mm, single.position_mm)
    assert multi.matched == single.matched
    found = np.array([t.position_mm for t in multi.targets])
    for truth in targets:
        assert np.linalg.norm(found - truth, axis=1).min() < 15.0
    assert 2 <= len(multi.targets) <= 4
    record = multi.record()
    assert record["targets"][0]["position_mm"] == record["position_mm"]
    for t in record["targets"]:
        c = np.array(t["covariance_mm2"])
        assert c.shape == (3, 3) and np.allclose(c, c.T)


def test_max_targets_bounds(profile):
    p = Pipeline(profile)
    for bad in (0, 17, 2.5, "4"):
        with pytest.raises(InputError):
            p.set_max_targets(bad)
    data = profile_to_dict(profile)
    for key, value in (("max_targets", 0), ("max_targets", 17), ("covariance_scale", 0.0)):
        bad = {**data, "scene": {**data["scene"], key: value}}
        with pytest.raises(ConfigError, match=f"scene.{key}"):
            profile_from_dict(bad)


def test_hundreds_of_echo_candidates_stay_bounded(profile, rng):
    """Noise everywhere (max_echoes 16 per channel): a bounded number of finite targets."""
    prof = with_scene(profile, max_targets=16, max_cost_mm=1000.0)
    prof = prof.replace(detect=dataclasses.replace(prof.detect, max_echoes=16, threshold=1.0))
    frames = rng.uniform(0, 3000, (4, 64))
    result = Pipeline(prof).process(frames, None)
    assert len(result.targets) <= 16
    for t in result.targets:
        assert np.all(np.isfinite(t.position_mm)) and np.all(np.isfinite(t.covariance_mm2))


def test_shared_echo_joins_target_missing_that_channel(profile):
    ch, e = geometry(profile)
    listening = np.ones(4, bool)
    a, b = np.array([0.0, 40.0, 150.0]), np.array([0.0, -40.0, 150.0])  # one range on 0 and 2
    pa, pb = predicted_paths(a, ch, e), predicted_paths(b, ch, e)
    paths = np.array([[pa[0], np.nan], [pa[1], pb[1]], [pa[2], np.nan], [pa[3], pb[3]]])
    taken = np.array([[True, False], [True, False], [True, False], [True, False]])
    matched_b = np.array([-1, 1, -1, 1])
    out = shared_echoes(matched_b, b, paths, taken, ch, e, listening, 6.0)
    assert out.tolist() == [0, 1, 0, 1]
    far = shared_echoes(matched_b, b + [0, 0, 40], paths, taken, ch, e, listening, 6.0)
    assert far.tolist() == [-1, 1, -1, 1]


def test_double_reflection_is_recognised(profile):
    ch, e = geometry(profile)
    facing = np.asarray(profile.geometry.facing, float)
    target = np.array([20.0, -30.0, 110.0])
    paths = predicted_paths(target, ch, e)
    double = paths + 2 * 110.0
    assert is_double_reflection(double, paths, target, e, facing, 20.0)
    other = predicted_paths(np.array([-60.0, 50.0, 300.0]), ch, e)
    assert not is_double_reflection(other, paths, target, e, facing, 20.0)


def test_static_model_loads_and_bad_model_warns(profile, tmp_path, caplog):
    model = load_static_model(profile)
    assert model.shape == (4, 64) and np.all(np.isfinite(model)) and model.max() > 1000
    assert load_static_model(with_scene(profile, static_model="")) is None
    bad = tmp_path / "bad.npz"
    np.savez(bad, median=np.zeros((3, 8)), mad=np.zeros((3, 8)))
    assert load_static_model(with_scene(profile, static_model=str(bad))) is None
    assert load_static_model(with_scene(profile, static_model=str(tmp_path / "none.npz"))) is None
    assert "static scene model" in caplog.text


def test_without_background_static_model_finds_vendored_targets(profile, subset):
    """Without a background, K = 4: the labelled target among the targets in most frames."""
    pipe = Pipeline(with_scene(profile, max_targets=4))
    keep = subset.truth_mm[:, 2] != 90.0
    hits = []
    for frames, truth in zip(subset.frames[keep][::3], subset.truth_mm[keep][::3], strict=True):
        found = [t.position_mm for t in pipe.process(frames, None).targets]
        hits.append(bool(found) and np.linalg.norm(np.array(found) - truth, axis=1).min() < 30)
    assert np.mean(hits) > 0.6


def test_scene_file_evaluate_and_max_targets_option(subset, tmp_path, capsys):
    import json

    from spiel_edge.cli import main
    from tools.train.build_scenes import compose

    frames, bgs = subset.frames.astype(float), subset.backgrounds.astype(float)
    a, b = 0, int(np.argmax(np.linalg.norm(subset.truth_mm - subset.truth_mm[0], axis=1)))
    truth = np.full((2, 3, 3), np.nan)
    truth[0, :1] = subset.truth_mm[a]
    truth[1, :2] = subset.truth_mm[[a, b]]
    path = tmp_path / "scenes.npz"
    np.savez(
        path,
        frames=np.array([frames[a], compose(frames, bgs, [a, b])]),
        backgrounds=np.array([np.full((4, 64), np.nan), bgs[a]]),
        truth_mm=truth,
        names=np.array(["single", "pair"]),
        split="test",
    )
    assert main(["evaluate", str(path), "--max-targets", "4", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["max_targets"] == 4 and set(out["by_targets"]) == {"1", "2"}
    assert out["by_targets"]["2"]["frames"] == 1
    assert main(["evaluate", str(path), "--max-targets", "17"]) == 2
    assert "--max-targets" in capsys.readouterr().err
    bad = tmp_path / "bad.npz"
    np.savez(bad, frames=np.zeros(3))
    assert main(["evaluate", str(bad)]) != 0
    assert "without frames, backgrounds, truth_mm and names" in capsys.readouterr().err
