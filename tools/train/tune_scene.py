"""Tune the scene stage's selection on a TRAINING scene file (tools/train/build_scenes.py).

Runs the pipeline's front stages (preprocess .. features) once per acquisition, then, for
every combination of the grid, only the scene association and the locate step, and prints
the per-number-of-targets figures of ``spiel-edge evaluate`` (one JSON line per setting):

    python -m tools.train.tune_scene /tmp/train.npz --max-targets 4 \\
        --grid max_cost_mm=5,10,20 --grid share_penalty_mm=10,40

Only for choosing thresholds on the training split: report on validation with
``spiel-edge evaluate``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json

import numpy as np

from spiel_edge.measure.scenes import SceneTally, load_scenes
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile


def cache_front(pipeline, scenes) -> list:
    """(features, counts, raw, effective background, truths) per acquisition."""
    cached, captured = [], {}

    def capture(feats, counts, hyps, raw, background):
        captured.update(feats=feats, counts=counts, raw=raw, background=background)
        return original(feats, counts, hyps, raw, background)

    original = pipeline.locate_hypotheses
    pipeline.locate_hypotheses = capture
    try:
        for frames, bg, truth in zip(
            scenes["frames"], scenes["backgrounds"], scenes["truth_mm"], strict=True
        ):
            pipeline.process(frames, None if np.isnan(bg).all() else bg)
            truths = truth[np.isfinite(truth).all(axis=1)]
            cached.append(
                (*(captured[k] for k in ("feats", "counts", "raw", "background")), truths)
            )
    finally:
        pipeline.locate_hypotheses = original
    return cached


def run_setting(pipeline, cached, max_targets: int) -> dict:
    pipeline.set_max_targets(max_targets)
    tally = SceneTally()
    for feats, counts, raw, background, truths in cached:
        hyps = pipeline.scene(feats, counts)
        tally.add(pipeline.locate_hypotheses(feats, counts, hyps, raw, background), truths)
    return tally.summary()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes")
    ap.add_argument("--max-targets", type=int, default=4)
    ap.add_argument("--grid", action="append", default=[], help="KEY=v1,v2 ([scene] key)")
    ap.add_argument("--limit", type=int, default=0, help="first N acquisitions per group")
    args = ap.parse_args(argv)
    profile = load_profile()
    pipeline = build_pipeline(profile, fused=False)
    scenes = load_scenes(args.scenes)
    if args.limit:
        n_true = np.isfinite(scenes["truth_mm"]).all(axis=2).sum(axis=1)
        keep = np.concatenate([np.flatnonzero(n_true == n)[: args.limit] for n in (1, 2, 3)])
        scenes = {k: v[keep] if k != "split" else v for k, v in scenes.items()}
    cached = cache_front(pipeline, scenes)
    keys = [g.split("=")[0] for g in args.grid]
    values = [[parse_value(v) for v in g.split("=")[1].split(",")] for g in args.grid]
    for setting in itertools.product(*values):
        kw = dict(zip(keys, setting, strict=True))
        pipeline.profile = profile.replace(scene=dataclasses.replace(profile.scene, **kw))
        summary = run_setting(pipeline, cached, args.max_targets)
        print(json.dumps({"setting": kw, "by_targets": summary}), flush=True)
    return 0


def parse_value(text: str):
    """A grid value from the command line: bool, int, float or the text."""
    if text in ("true", "false"):
        return text == "true"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


if __name__ == "__main__":
    raise SystemExit(main())
