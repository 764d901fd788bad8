"""Per-channel echo recall of the front end on a TRAINING scene file (tools/train/build_scenes.py).

For each true target of each acquisition and each channel: is there a detected echo (after
MEMG, the ToA the associator sees) within 0.5 / 1 sample of its ideal ToA (labelled position,
calibrated geometry and delays, plus a per-channel estimator offset fitted on the file's
single-target frames)? Split by number of targets and by how near another target's ideal ToA
is on that channel. One JSON line per setting of the grid ([detect] / [memg] profile keys):

    python -m tools.train.build_scenes $D --split train -o /tmp/res_train.npz
    python -m tools.research.echo_recall /tmp/res_train.npz --grid detect.threshold=20,30 \\
        --grid detect.max_echoes=6,10

Only for choosing front-end settings on the training split (docs/localisation.md, "Two
targets at one range: the front end"); report on validation with ``spiel-edge evaluate``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json

import numpy as np

from spiel_edge.measure.scenes import load_scenes
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.detect import detect
from spiel_edge.pipeline.stages.features import TOA_COLUMN, echo_features
from spiel_edge.pipeline.stages.memg import fit_memg
from spiel_edge.pipeline.stages.preprocess import preprocess
from spiel_edge.pipeline.stages.split import split_merged
from spiel_edge.profile.schema import load_profile
from tools.research.echo_recall_steps import (
    GAP_EDGES,
    gap_bin,
    ideal_toa,
    nearest_echo,
    shared_echo,
    truth_gap,
)
from tools.train.tune_scene import parse_value

TOLS = (0.5, 1.0)


def front_end(pipe: Pipeline, frames: np.ndarray, background: np.ndarray | None):
    """(ToA after MEMG, detected peak samples (both (channels, echoes), NaN-padded), counts)
    as Pipeline.process computes them."""
    p = pipe.profile
    bg = pipe.static_model if background is None else background
    y = preprocess(frames, bg, blind_zone=p.preprocess.blind_zone_samples)
    d = p.detect
    peaks, counts = detect(
        y,
        threshold=d.threshold,
        hysteresis=d.hysteresis,
        min_amplitude=d.min_amplitude,
        max_echoes=d.max_echoes,
        first_sample=p.preprocess.blind_zone_samples,
    )
    m = p.memg
    params = fit_memg(y, peaks, counts, mu_window=m.mu_window, max_iterations=m.max_iterations)
    if m.split_merged:
        peaks, counts, params = split_merged(
            y,
            peaks,
            counts,
            params,
            min_sigma=m.split_min_sigma,
            max_cost_ratio=m.split_max_cost_ratio,
            mu_window=m.mu_window,
            max_iterations=m.max_iterations,
        )
    toa = echo_features(y, params, peaks, p.memg.toa)[:, :, TOA_COLUMN]
    return toa, np.where(peaks >= 0, peaks, np.nan).astype(np.float64), counts


def collect(pipe: Pipeline, scenes: dict) -> list:
    """Per acquisition: (number of truths, ideal ToA without offset, echo ToAs, counts,
    detected peaks, name)."""
    g, mmps = pipe.profile.geometry, pipe.profile.mm_per_sample
    out = []
    for frames, bg, truth, name in zip(
        scenes["frames"], scenes["backgrounds"], scenes["truth_mm"], scenes["names"], strict=True
    ):
        truths = truth[np.isfinite(truth).all(axis=1)].astype(np.float64)
        paths = np.array([g.echo_paths_mm(t) for t in truths])
        toa, peaks, counts = front_end(
            pipe, frames.astype(np.float64), None if np.isnan(bg).all() else bg
        )
        out.append(
            (len(truths), ideal_toa(paths, mmps, pipe.delays), toa, counts, peaks, str(name))
        )
    return out


def fit_offset(rows: list) -> np.ndarray:
    """Per channel median (echo ToA − ideal ToA) over single-target acquisitions, nearest echo
    within 2 samples: the MEMG mode's own bias against the calibrated delays."""
    d = np.array([nearest_echo(toa, ideal)[0] for n, ideal, toa, *_ in rows if n == 1])
    d = np.where(np.abs(d) < 2.0, d, np.nan)
    return np.nanmedian(d, axis=0)


def alone_hits(rows: list, offset: np.ndarray) -> dict[str, np.ndarray]:
    """Per single-target recording name: per channel, an echo within 1 sample of its ideal
    ToA when the recording is processed alone (its own background)."""
    out = {}
    for n, ideal, toa, *_, name in rows:
        if n == 1:
            d = np.abs(nearest_echo(toa, ideal + offset))[0]
            out[name] = np.where(np.isfinite(d), d, np.inf) <= 1.0
    return out


def summarise(rows: list, offset: np.ndarray, max_echoes: int, alone: dict | None = None) -> dict:
    """Recall figures by number of truths; with ``alone`` (:func:`alone_hits`) also the
    recall of composed truths' echoes that are recalled when their recording is alone."""
    by: dict = {}
    for n in (1, 2, 3):
        sel = [r for r in rows if r[0] == n]
        if not sel:
            continue
        dist, gaps, shared, full, peak, solo = [], [], [], [], [], []
        for _, ideal, toa, counts, peaks, name in sel:
            if alone is not None and n > 1:
                solo.append(np.array([alone[part] for part in name.split("+")]))
            ideal = ideal + offset
            dist.append(nearest_echo(toa, ideal))
            peak.append(nearest_echo(peaks, ideal))
            gaps.append(truth_gap(ideal))
            shared.append(shared_echo(toa, ideal, 1.0))
            full.append(np.broadcast_to(counts >= max_echoes, ideal.shape))
        d, gap = np.abs(np.vstack(dist)), np.vstack(gaps)
        d = np.where(np.isfinite(d), d, np.inf)
        hit1 = d <= 1.0
        per_truth3 = (hit1.sum(axis=1) >= 3).reshape(len(sel), n)
        entry = {f"recall_{t}": round(float((d <= t).mean()), 4) for t in TOLS}
        p = np.abs(np.vstack(peak))
        entry["detected_peak_1.0"] = round(
            float((np.where(np.isfinite(p), p, np.inf) <= 1.0).mean()), 4
        )
        entry["truths_3ch_at_1"] = round(float(per_truth3.mean()), 4)
        entry["all_truths_3ch_at_1"] = round(float(per_truth3.all(axis=1).mean()), 4)
        entry["shared_echo_at_1"] = round(float(np.vstack(shared).mean()), 4)
        entry["channels_at_max_echoes"] = round(float(np.vstack(full).mean()), 4)
        if n > 1:
            b = gap_bin(gap)
            names = [f"<{GAP_EDGES[0]:g}"]
            names += [f"{lo:g}-{hi:g}" for lo, hi in zip(GAP_EDGES, GAP_EDGES[1:], strict=False)]
            names += [f">={GAP_EDGES[-1]:g}"]
            ok = np.vstack(solo) if solo else np.ones_like(hit1)
            if solo:
                entry["alone_recall_1"] = round(float(ok.mean()), 4)
                entry["recall_1_given_alone"] = round(float(hit1[ok].mean()), 4)
            entry["by_gap"] = {
                name: {
                    "share": round(float((b == k).mean()), 4),
                    "recall_1": _share(hit1[b == k]),
                    "recall_1_given_alone": _share(hit1[(b == k) & ok]) if solo else None,
                }
                for k, name in enumerate(names)
            }
        by[str(n)] = entry
    return by


def _share(hits: np.ndarray) -> float | None:
    return round(float(hits.mean()), 4) if hits.size else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes")
    ap.add_argument("--grid", action="append", default=[], help="SECTION.KEY=v1,v2 (detect, memg)")
    ap.add_argument(
        "--singles",
        help="scene file of the same split's single frames WITH background "
        "(build_scenes --pairs 0 --triples 0 --single-background): recall given alone",
    )
    ap.add_argument("--limit", type=int, default=0, help="first N acquisitions per group")
    args = ap.parse_args(argv)
    base = load_profile()
    scenes = load_scenes(args.scenes)
    if args.limit:
        n_true = np.isfinite(scenes["truth_mm"]).all(axis=2).sum(axis=1)
        keep = np.concatenate([np.flatnonzero(n_true == n)[: args.limit] for n in (1, 2, 3)])
        scenes = {k: v[keep] if k != "split" else v for k, v in scenes.items()}
    pipe = Pipeline(base)
    singles = load_scenes(args.singles) if args.singles else None
    # the offset is fitted with the shipped front end and kept fixed over the grid
    offset = fit_offset(collect(pipe, singles if singles is not None else scenes))
    print(json.dumps({"offset_samples": [round(float(v), 3) for v in offset]}), flush=True)
    keys = [g.split("=")[0] for g in args.grid]
    values = [[parse_value(v) for v in g.split("=")[1].split(",")] for g in args.grid]
    for setting in itertools.product(*values):
        profile = base
        for key, value in zip(keys, setting, strict=True):
            section, name = key.split(".")
            spec = dataclasses.replace(getattr(profile, section), **{name: value})
            profile = profile.replace(**{section: spec})
        pipe.profile = profile
        rows = collect(pipe, scenes)
        alone = None if singles is None else alone_hits(collect(pipe, singles), offset)
        summary = summarise(rows, offset, profile.detect.max_echoes, alone)
        print(
            json.dumps({"setting": dict(zip(keys, setting, strict=True)), "by_targets": summary}),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
