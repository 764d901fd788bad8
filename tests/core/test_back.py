"""The one-target kernel (pipeline/compiled/one_target.py) gives the staged Result bit for bit; the association MLP
in numba agrees with onnxruntime; verified weights load without onnxruntime."""

import dataclasses
import os
import subprocess
import sys

import numpy as np
import onnx
import pytest
from onnx import helper

from spiel_edge.errors import InputError
from spiel_edge.pipeline.compiled import abi
from spiel_edge.pipeline.compiled.fused import FusedPipeline
from spiel_edge.pipeline.learned import mlp, verified_models
from spiel_edge.pipeline.learned.associate_onnx import (
    OnnxAssociator,
    default_model_path,
    load_session,
)
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.echo_timing import EchoTiming
from spiel_edge.sim.synthetic import ring_profile, synthesize
from tests.core.test_fused import assert_same


def _same_on(staged: Pipeline, frames, backgrounds, prior: int | None = None) -> int:
    """Assert fused == staged on every acquisition; the number located."""
    fast = FusedPipeline(staged)
    located = 0
    for f, b in zip(frames, backgrounds, strict=True):
        result = fast.process(f, b)
        assert_same(result, staged.process(f, b))
        located += result.position_mm is not None
    assert fast.kernel == "one_target", "the compiled path was not used"
    if prior is not None:
        assert fast.config.ints[abi.I_PRIOR] == prior
    return located


def test_back_kernel_with_the_numba_mlp_equals_staged(profile, subset):
    assoc = OnnxAssociator(profile)
    assert assoc.engine == "numba"
    staged = Pipeline(profile, assoc)
    located = _same_on(staged, subset.frames, subset.backgrounds, abi.PRIOR_MLP)
    assert located > 0.9 * len(subset.frames)


def test_a_model_in_onnxruntime_runs_the_staged_path_whole(profile, subset):
    assoc = OnnxAssociator(profile)
    assoc.mlp, assoc.engine, assoc.session = None, "onnxruntime", load_session(assoc.model_path)
    staged = Pipeline(profile, assoc)
    fast = FusedPipeline(staged)
    for f, b in zip(subset.frames[:10], subset.backgrounds[:10], strict=True):
        assert_same(fast.process(f, b), staged.process(f, b))
    assert fast.kernel is None
    bad = subset.frames[0].copy()
    bad[2, 5] = np.inf
    with pytest.raises(InputError, match="frames contains NaN or infinite"):
        fast.process(bad, subset.backgrounds[0])


@pytest.mark.parametrize("estimator", ["log_parabola", "none"])
def test_back_kernel_without_the_correction_equals_staged(profile, subset, estimator):
    timing = EchoTiming(estimator, 2, profile.preprocess.blind_zone_samples, None)
    staged = Pipeline(profile, echo_timing=timing)
    _same_on(staged, subset.frames[:40], [None] * 40)  # static background model
    _same_on(staged, subset.frames[40:80], subset.backgrounds[40:80])


def test_back_kernel_hypothesis_search_equals_staged(rng):
    prof = ring_profile(8, 256)  # 8 channels: hypothesise-and-verify association
    frames, backgrounds = [], []
    for i in range(4):
        target = np.c_[rng.uniform(-80, 80, (1, 2)), rng.uniform(100, 300, 1)]
        f, b = synthesize(prof, target, seed=i)
        frames.append(f)
        backgrounds.append(b)
    frames.append(np.zeros((8, 256)))  # nothing to find: the reason, as staged
    backgrounds.append(np.zeros((8, 256)))
    _same_on(Pipeline(prof), frames, backgrounds, abi.PRIOR_NONE)


def test_several_targets_use_the_scene_kernel_greedy_keeps_the_staged_steps(profile, subset):
    staged = Pipeline(profile, max_targets=3)
    fast = FusedPipeline(staged)
    for f, b in zip(subset.frames[:20], subset.backgrounds[:20], strict=True):
        assert_same(fast.process(f, b), staged.process(f, b))
    assert fast.kernel == "several_targets"
    staged.set_max_targets(1)  # a new scene: the one-target kernel
    fast.process(subset.frames[0], subset.backgrounds[0])
    assert fast.kernel == "one_target"
    greedy = profile.replace(scene=dataclasses.replace(profile.scene, selection="greedy"))
    staged = Pipeline(greedy, max_targets=3)
    fast = FusedPipeline(staged)
    for f, b in zip(subset.frames[:20], subset.backgrounds[:20], strict=True):
        assert_same(fast.process(f, b), staged.process(f, b))
    assert fast.kernel is None


def test_numba_mlp_matches_onnxruntime(profile, subset):
    path = default_model_path()
    weights = mlp.read_mlp(path.read_bytes())
    session = load_session(path)
    probe = np.random.default_rng(7).normal(size=(512, 8)) * weights[1] * 2 + weights[0]
    staged = Pipeline(profile)
    real = [
        staged.process(f, b)
        for f, b in zip(subset.frames[:30], subset.backgrounds[:30], strict=True)
    ]
    rows = np.concatenate([r.features[np.isfinite(r.features[:, :, 6])] for r in real])
    for x in (probe.astype(np.float32), rows.astype(np.float32)):
        score, emb = mlp.evaluate(x, weights)
        ref_score, ref_emb = session.run(["score", "embedding"], {"features": x})
        assert np.max(np.abs(score - ref_score[:, 0])) <= 1e-5
        assert np.max(np.abs(emb - ref_emb)) <= 1e-5


def test_mlp_scores_equal_mlp_row_bit_for_bit(profile, subset):
    """The echoes scored side by side (the back kernels' prior) == one row at a time."""
    weights = mlp.read_mlp(default_model_path().read_bytes())
    staged = Pipeline(profile)
    rows = np.concatenate(
        [staged.process(f).features[:, :, :] for f in subset.frames[:40]]
    ).reshape(-1, mlp.N_INPUT)
    probe = np.random.default_rng(3).normal(size=(300, 8)) * weights[1] * 3 + weights[0]
    for x in (rows[np.isfinite(rows).all(axis=1)], probe, probe[:1], probe[:0]):
        x = np.ascontiguousarray(x, dtype=np.float32)
        out = np.empty(len(x), np.float32)
        mlp.mlp_scores(x, len(x), *weights, out)
        z, h0, h1 = np.empty(8), np.empty(weights[2].shape[0]), np.empty(weights[4].shape[0])
        emb = np.empty(weights[6].shape[0])
        one = [mlp.mlp_row(r, *weights, z, h0, h1, emb) for r in x]
        assert np.array_equal(out, np.array(one, np.float32))


def test_unknown_graph_stays_on_onnxruntime(profile, tmp_path):
    model = onnx.load(str(default_model_path()))
    sigmoid = model.graph.node[-1]
    sigmoid.output[0] = "score_raw"
    model.graph.node.append(helper.make_node("Identity", ["score_raw"], ["score"]))
    path = tmp_path / "extra_op.onnx"
    onnx.save(model, str(path))
    with pytest.raises(Exception, match="not the known MLP"):
        mlp.read_mlp(path.read_bytes())
    assoc = OnnxAssociator(profile, path)
    assert assoc.engine == "onnxruntime" and assoc.mlp is None
    assert not list(verified_models.cache_dir().glob("extra_op-*"))


def test_changed_weights_are_verified_again_and_stored(profile, tmp_path):
    model = onnx.load(str(default_model_path()))
    bias = next(t for t in model.graph.initializer if t.name == "head.bias")
    bias.raw_data = np.array([0.25], np.float32).tobytes()
    path = tmp_path / "retrained.onnx"
    onnx.save(model, str(path))
    assoc = OnnxAssociator(profile, path)
    assert assoc.engine == "numba" and assoc.session is not None  # checked with onnxruntime
    stored = verified_models.cache_dir() / verified_models.file_name(
        path, verified_models.digest(path.read_bytes())
    )
    assert stored.is_file()
    again = OnnxAssociator(profile, path)
    assert again.engine == "numba" and again.session is None  # from the stored weights
    # a stored file whose hash does not match is ignored
    other = tmp_path / "other.onnx"
    other.write_bytes(path.read_bytes() + b"")  # same bytes, other name: its own lookup
    bad = verified_models.cache_dir() / verified_models.file_name(other, "0" * 64)
    bad.write_bytes(stored.read_bytes())
    assert verified_models.load(other, "0" * 64, mlp.WEIGHT_NAMES) is None


def test_shipped_models_load_without_onnxruntime():
    code = (
        "import sys\n"
        "from spiel_edge.profile.schema import load_profile\n"
        "from spiel_edge.pipeline.factory import build_pipeline\n"
        "p = build_pipeline(load_profile('spiel-icra23'))\n"
        "assert p.pipeline.associator.engine == 'numba'\n"
        "assert p.pipeline.echo_timing.correction.engine == 'numba'\n"
        "assert 'onnxruntime' not in sys.modules, 'onnxruntime imported'\n"
    )
    env = dict(os.environ, SPIEL_EDGE_MODEL_CACHE=os.environ["SPIEL_EDGE_MODEL_CACHE"])
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def test_rf_profile_equals_staged():
    prof = ring_profile(8, 256)
    rf = dataclasses.replace(
        prof, acquisition=dataclasses.replace(prof.acquisition, signal="rf", carrier_hz=5000.0)
    )
    f = 200.0 * np.sin(np.arange(256) * 2 * np.pi * 5000 / 22000)[None, :] * np.ones((8, 1))
    _same_on(Pipeline(rf), [f], [f * 0.5])
