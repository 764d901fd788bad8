"""The several-target kernel's pieces (pipeline/compiled/scene_steps.py, scene_geometry.py) against the
staged functions they replace, and the fixed-order sums against plain numpy."""

import math

import numpy as np
import pytest

from spiel_edge.pipeline.compiled import scene_steps as back_scene
from spiel_edge.pipeline.stages import scene
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.pipeline.stages.scene import SceneAssociator, is_double_reflection, shared_echoes
from spiel_edge.pipeline.stages.scene_geometry import distance3, dot3, height3, predicted_paths_into


def _random_pool(rng, n, n_ch, n_echoes):
    choices = rng.integers(-1, n_echoes, (n, n_ch))
    choices[:, :3] = rng.integers(0, n_echoes, (n, 3))  # at least 3 channels, as the pool
    rng.shuffle(choices, axis=1)
    costs = np.sort(rng.normal(0.0, 8.0, n))
    costs[rng.integers(0, n, n // 4)] = costs[0]  # ties: the stable order matters
    return choices, np.sort(costs)


@pytest.mark.parametrize("keep_best", [True, False])
def test_hypotheses_equal_the_joint_choice(profile, rng, monkeypatch, keep_best):
    geo = GeometricAssociator(profile)
    for trial in range(300):
        n = int(rng.integers(1, 49))
        choices, costs = _random_pool(rng, n, 4, 4)
        k = int(rng.integers(2, 9))
        floats = np.array([rng.uniform(-5, 20), rng.uniform(0, 40), rng.uniform(-10, 10), 0, 0, 0])
        extra = int(rng.integers(3, 5))
        sa = SceneAssociator(
            geo,
            k,
            floats[0],
            floats[1],
            extra,
            "joint",
            geo.missing_penalty_mm + floats[2],
            keep_best,
        )
        assert sa.missing_shift_mm == pytest.approx(floats[2])
        floats[2] = sa.missing_shift_mm
        monkeypatch.setattr(scene, "combination_pool", lambda *a, c=choices, s=costs: (c, s))
        expected = sa._joint(None, np.zeros(4, np.int64), None)
        out_m = np.empty((k, 4), np.int64)
        out_c = np.empty(k)
        ints = np.array([k, sa.extra_min_channels, keep_best], np.int64)
        n_hyp = back_scene.hypotheses(choices, costs, 4, ints, floats, out_m, out_c)
        assert n_hyp == len(expected), trial
        for (m, c), got_m, got_c in zip(expected, out_m, out_c, strict=False):
            assert np.array_equal(m, got_m) and c == got_c, trial


def test_share_equals_shared_echoes(profile, rng):
    ch = np.asarray(profile.geometry.channels_mm, float)
    e = np.asarray(profile.geometry.emitter_mm, float)
    for _ in range(500):
        position = np.array([*rng.uniform(-80, 80, 2), rng.uniform(80, 400)])
        pred = scene.predicted_paths(position, ch, e)
        paths = pred[:, None] + rng.normal(0, 8, (4, 5))
        paths[rng.random((4, 5)) < 0.2] = np.nan
        taken = rng.random((4, 5)) < 0.6
        matched = rng.integers(-1, 5, 4)
        listening = rng.random(4) < 0.9
        tol = float(rng.uniform(0, 12))
        expected = shared_echoes(matched, position, paths, taken, ch, e, listening, tol)
        out = np.empty(4, np.int64)
        pred_k = np.empty(4)
        predicted_paths_into(position, ch, e, pred_k)
        changed = back_scene.share(matched, pred_k, paths, taken, listening, tol, out)
        assert np.array_equal(out, expected) and changed == bool((expected != matched).any())


def test_double_reflection_equals_staged(profile, rng):
    ch = np.asarray(profile.geometry.channels_mm, float)
    e = np.asarray(profile.geometry.emitter_mm, float)
    facing = np.asarray(profile.geometry.facing, float)
    found = 0
    for _ in range(500):
        other = np.array([*rng.uniform(-80, 80, 2), rng.uniform(-50, 300)])
        other_paths = scene.predicted_paths(other, ch, e)
        paths = other_paths + 2 * other[2] + rng.normal(0, 6, 4)
        paths[rng.random(4) < 0.15] = np.nan
        tol = float(rng.uniform(0, 20))
        expected = is_double_reflection(paths, other_paths, other, e, facing, tol)
        assert back_scene.double_reflection(paths, other_paths, other, e, facing, tol) == expected
        found += expected
    assert 0 < found < 500


def test_fixed_order_sums_equal_numpy_sums(rng):
    """The sums the scene stage uses (staged and fused) are the plain elementwise ones."""
    ch = rng.normal(0, 40, (6, 3))
    for _ in range(2000):
        p, e, f = rng.normal(0, 200, 3), rng.normal(0, 5, 3), rng.normal(0, 1, 3)
        out = np.empty(6)
        predicted_paths_into(p, ch, e, out)
        ref = np.sqrt(np.sum((p - e) ** 2)) + np.sqrt(np.sum((p - ch) ** 2, axis=1))
        assert np.array_equal(out, ref)
        assert height3(p, e, f) == np.sum((p - e) * f) == dot3(p - e, f)
        assert distance3(p, e) == math.sqrt(np.sum((p - e) ** 2))


@pytest.mark.parametrize("association", ["geometric", "onnx"])
@pytest.mark.parametrize("k", [1, 4])
def test_packed_config_holds_every_constant_exactly(profile, association, k):
    """kernel_config packs the pipeline's constants into four buffers by dtype; the kernels'
    views (view_1d / view_2d with the table's slot numbers) give each array back with its dtype,
    shape and bits; an array of another dtype turns the kernel off (the staged path)."""
    from spiel_edge.pipeline.compiled import abi
    from spiel_edge.pipeline.factory import build_pipeline

    pipeline = build_pipeline(profile, association, fused=False)
    pipeline.set_max_targets(k)
    values = pipeline.kernel_constants()
    config = abi.kernel_config(pipeline)
    assert values is not None and config is not None
    assert config.ints.dtype == np.int64
    assert config.ints.tolist() == [
        abi.PRIORS.index(values[n]) if n == "prior" else
        abi.TIMINGS.index(values[n]) if n == "timing" else int(values[n])
        for n in abi.INTS
    ]  # fmt: skip
    buffers = (config.f64, config.f32, config.i64, config.flags)
    for field in abi.CONSTANTS.fields:
        slot = abi.CONSTANTS.slot(field.name)
        buf = buffers[abi.CONSTANTS.buffer_of(field.name)]
        got = (
            abi.view_2d(buf, config.layout, slot)
            if len(field.dims) == 2
            else abi.view_1d(buf, config.layout, slot)
        )
        if field.name == "share_listening" and k == 1:
            assert got.size == 0  # the scene's constants are empty for one target
        elif field.name in values:
            want = np.asarray(values[field.name])
            assert got.dtype == want.dtype, field.name
            assert got.size == want.size and got.tobytes() == want.tobytes(), field.name
            assert got.shape == (want.shape or (1,)), field.name
    floats = abi.view_1d(config.f64, config.layout, abi.L_FLOATS)
    assert floats.tolist() == [values[n] for n in abi.FLOATS]
    scene = abi.view_1d(config.f64, config.layout, abi.L_SCENE_FLOATS)
    assert scene.tolist() == ([values[n] for n in abi.SCENE_FLOATS] if k > 1 else [])
    wrong = dict(values, w0=np.zeros((2, 2)))  # float64 weights
    pipeline.kernel_constants = lambda: wrong
    assert abi.kernel_config(pipeline) is None
