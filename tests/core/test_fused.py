"""The fused path gives the staged path's Result bit for bit, and falls back when it must."""

import dataclasses

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.pipeline import fused, run
from spiel_edge.pipeline.fused import FusedPipeline, unsupported_stages
from spiel_edge.pipeline.run import Pipeline
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


def test_fused_validates_like_staged(profile, subset):
    fast = FusedPipeline(Pipeline(profile))
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
            Pipeline(profile).process(*args)


def test_unknown_stage_or_subclass_falls_back_to_staged(profile, subset, monkeypatch):
    calls = []

    class Extra(Pipeline):
        def process(self, frames, background=None, *, timed=False):
            calls.append(1)
            return super().process(frames, background, timed=timed)

    fast = FusedPipeline(Extra(profile))
    assert fast.fallback == ["Extra.process"]
    fast.process(subset.frames[0], subset.backgrounds[0])
    assert calls == [1]
    monkeypatch.setattr(run, "STAGES", (*run.STAGES[:5], "timing", "locate"))
    assert unsupported_stages(Pipeline(profile)) == ["timing"]  # a step fused.py lacks
    staged = Pipeline(profile)
    seen = []
    monkeypatch.setattr(staged, "process", lambda *a, **k: seen.append(1) or "staged")
    assert FusedPipeline(staged).process(subset.frames[0]) == "staged" and seen == [1]
    monkeypatch.setitem(fused.BACK_STEPS, "timing", lambda pipeline, state: None)
    assert unsupported_stages(Pipeline(profile)) == []
