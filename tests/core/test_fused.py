"""The fused path gives the staged path's Result bit for bit, and falls back when it must."""

import dataclasses

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.pipeline import staged as run
from spiel_edge.pipeline.compiled import fused
from spiel_edge.pipeline.compiled.fused import FusedPipeline, unsupported_stages
from spiel_edge.pipeline.learned.associate_onnx import OnnxAssociator, load_session
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.sim.synthetic import ring_profile, synthesize


def assert_same(a: run.Result, b: run.Result) -> None:
    assert a.reason == b.reason and a.matched == b.matched and a.echoes == b.echoes
    if a.position_mm is None:
        assert b.position_mm is None
    else:
        assert np.array_equal(a.position_mm, b.position_mm) and a.residual_mm == b.residual_mm
    assert np.array_equal(a.features, b.features, equal_nan=True)
    assert np.array_equal(a.counts, b.counts)
    assert [t.record() for t in a.targets] == [t.record() for t in b.targets]


def test_fused_equals_staged_on_real_frames(profile, subset):
    staged = Pipeline(profile)
    fast = FusedPipeline(staged)
    assert not fast.fallback
    for f, b in zip(subset.frames, subset.backgrounds, strict=True):
        assert_same(fast.process(f, b), staged.process(f, b))
        assert_same(fast.process(f.astype(np.uint16)), staged.process(f.astype(np.uint16)))


def test_fused_equals_staged_on_synthetic_and_rf(rng):
    prof = ring_profile(8, 256)
    staged = Pipeline(prof)
    fast = FusedPipeline(staged)
    for i in range(4):
        targets = np.c_[rng.uniform(-80, 80, (2, 2)), rng.uniform(100, 300, 2)]
        f, b = synthesize(prof, targets, seed=i)
        assert_same(fast.process(f, b), staged.process(f, b))
    rf = dataclasses.replace(
        prof,
        acquisition=dataclasses.replace(prof.acquisition, signal="rf", carrier_hz=5000.0),
    )
    f = 200.0 * np.sin(np.arange(256) * 2 * np.pi * 5000 / 22000)[None, :] * np.ones((8, 1))
    assert_same(FusedPipeline(Pipeline(rf)).process(f, f * 0.5), Pipeline(rf).process(f, f * 0.5))


def test_fused_equals_staged_with_the_merged_echo_split(profile, subset, rng):
    """[memg] split_merged: both paths call the same split kernel; it does split here."""
    memg = dataclasses.replace(profile.memg, split_merged=True, split_min_sigma=2.0)
    on = Pipeline(profile.replace(memg=memg))
    off, fast = Pipeline(profile), FusedPipeline(on)
    assert not fast.fallback
    extra = 0
    for f, b in zip(subset.frames, subset.backgrounds, strict=True):
        for bg in (b, None):  # without a background: the static stand-in, wider humps
            a = on.process(f, bg)
            assert_same(fast.process(f, bg), a)
            extra += int(a.counts.sum() - off.process(f, bg).counts.sum())
    assert extra > 0
    prof = ring_profile(8, 256)
    prof = prof.replace(memg=dataclasses.replace(prof.memg, split_merged=True))
    for i in range(3):
        near = rng.uniform(150, 250)
        targets = np.array([[0.0, 0.0, near], [10.0, -5.0, near + 3.0]])
        f, b = synthesize(prof, targets, seed=i)
        assert_same(FusedPipeline(Pipeline(prof)).process(f, b), Pipeline(prof).process(f, b))


@pytest.mark.parametrize("max_targets", [1, 4])  # one call: one_target's or several_targets'
def test_fused_validates_like_staged(profile, subset, max_targets):
    staged = Pipeline(profile, max_targets=max_targets)
    fast = FusedPipeline(staged)
    f, b = subset.frames[0], subset.backgrounds[0]
    bad = f.copy()
    bad[1, 3] = np.nan
    for args, match in (
        ((bad, b), "frames contains NaN"),
        ((f, bad), "background contains NaN"),
        ((f[:, :10], b), r"frames has shape \(4, 10\)"),
        ((f.astype(object), b), "frames must be numeric"),
    ):
        with pytest.raises(InputError, match=match):
            fast.process(*args)
        with pytest.raises(InputError, match=match):
            staged.process(*args)
        assert_same(fast.process(f, b), staged.process(f, b))  # nothing left behind
    assert fast.kernel is not None


def test_unknown_stage_or_subclass_falls_back_to_staged(profile, subset, monkeypatch):
    calls = []

    class Extra(Pipeline):
        def process(self, frames, background=None, *, timed=False):
            calls.append(1)
            return super().process(frames, background, timed=timed)

    fast = FusedPipeline(Extra(profile))
    assert fast.fallback == ["Extra (not compiled_equivalent)"]
    fast.process(subset.frames[0], subset.backgrounds[0])
    assert calls == [1]

    class OwnTarget(Pipeline):
        def locate_target(self, *args):
            return super().locate_target(*args)

    assert FusedPipeline(OwnTarget(profile)).fallback == ["OwnTarget (not compiled_equivalent)"]

    class SameSteps(Pipeline):  # a subclass may say the compiled path is still its own
        compiled_equivalent = True

    assert FusedPipeline(SameSteps(profile)).fallback == []
    monkeypatch.setattr(run, "STAGES", (*run.STAGES[:5], "timing", "locate"))
    assert unsupported_stages(Pipeline(profile)) == ["timing"]  # a step fused.py lacks
    staged = Pipeline(profile)
    seen = []
    monkeypatch.setattr(staged, "process", lambda *a, **k: seen.append(1) or "staged")
    assert FusedPipeline(staged).process(subset.frames[0]) == "staged" and seen == [1]
    monkeypatch.setattr(fused, "COMPILED_STAGES", run.STAGES)
    assert unsupported_stages(Pipeline(profile)) == []


def assert_same_targets(a: run.Result, b: run.Result) -> None:
    """Exact, unrounded: every target's position, covariance, rms, matched echoes and score."""
    assert a.reason == b.reason and a.matched == b.matched and a.residual_mm == b.residual_mm
    assert len(a.targets) == len(b.targets)
    for s, t in zip(a.targets, b.targets, strict=True):
        assert np.array_equal(s.position_mm, t.position_mm)
        assert np.array_equal(s.covariance_mm2, t.covariance_mm2)
        assert s.residual_mm == t.residual_mm and s.matched == t.matched and s.score == t.score


def _several_same(staged: Pipeline, frames, backgrounds) -> int:
    """fused == staged on every acquisition with and without its background, through the
    several-target kernel; the number of acquisitions with more than one target."""
    fast = FusedPipeline(staged)
    several = 0
    for f, b in zip(frames, backgrounds, strict=True):
        for bg in (b, None):  # None: the static model stands in
            a = fast.process(f, bg)
            s = staged.process(f, bg)
            assert_same(a, s)
            assert_same_targets(a, s)
            several += len(a.targets) > 1
    assert fast.kernel == "several_targets"
    return several


@pytest.mark.parametrize("k", [2, 4, 8])
@pytest.mark.parametrize("association", ["geometric", "numba_mlp"])
def test_fused_equals_staged_with_several_targets(profile, subset, k, association):
    assoc = GeometricAssociator(profile) if association == "geometric" else OnnxAssociator(profile)
    staged = Pipeline(profile, assoc, max_targets=k)
    assert _several_same(staged, subset.frames, subset.backgrounds) > 0


def test_fused_equals_staged_with_several_targets_and_other_scene_settings(profile, subset):
    """No K = 1 pick kept first, a dearer birth, wide share / double / separation tolerances
    (shared echoes and double reflections are frequent here), and the model in onnxruntime
    (then the staged path runs whole)."""
    scene = dataclasses.replace(
        profile.scene,
        keep_best=False,
        max_cost_mm=30.0,
        share_tolerance_mm=15.0,
        double_tolerance_mm=40.0,
        min_separation_mm=60.0,
    )
    prof = profile.replace(scene=scene)
    assert _several_same(Pipeline(prof, max_targets=4), subset.frames, subset.backgrounds) > 0
    assoc = OnnxAssociator(prof)
    assoc.mlp, assoc.engine, assoc.session = None, "onnxruntime", load_session(assoc.model_path)
    staged = Pipeline(prof, assoc, max_targets=3)
    fast = FusedPipeline(staged)  # the model in onnxruntime: the staged path whole
    for f, b in zip(subset.frames[:20], subset.backgrounds[:20], strict=True):
        assert_same_targets(fast.process(f, b), staged.process(f, b))
    assert fast.kernel is None


def test_fused_equals_staged_with_several_synthetic_targets(rng):
    prof = ring_profile(6, 256)  # 6 channels: still the joint selection
    staged = Pipeline(prof, max_targets=4)
    frames, backgrounds = [], []
    for i in range(6):
        near = rng.uniform(150, 250)
        targets = np.array([[0.0, 40.0, near], [0.0, -40.0, near + 1.0], [30.0, 0.0, near + 60]])
        f, b = synthesize(prof, targets, seed=i)
        frames.append(f)
        backgrounds.append(b)
    frames.append(np.zeros((6, 256)))  # nothing to find: the reason, as staged
    backgrounds.append(np.zeros((6, 256)))
    _several_same(staged, frames, backgrounds)
