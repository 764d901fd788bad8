"""Ablation table and model card of the learned ToA correction (``tools.train.train_toa_correction``)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from spiel_edge.pipeline.learned.toa_correction import MAX_CORRECTION
from spiel_edge.pipeline.stages.echo_timing import n_toa_features
from spiel_edge.profile.schema import Profile
from tools.train import toa_correction_data as tcd


def corrected(model):
    """toa_of(case) for the refined ToA minus the model's clipped prediction (as at runtime)."""

    def toa_of(c):
        ok = np.all(np.isfinite(c.features), axis=1)
        out = c.refined.copy()
        if ok.any():
            pred = np.clip(
                model.predict(c.features[ok].astype(np.float32)), -MAX_CORRECTION, MAX_CORRECTION
            )
            out[ok] = c.refined[ok] - pred
        return out

    return toa_of


def _stats(errors: np.ndarray, z: np.ndarray, keep: np.ndarray) -> tuple:
    e = errors[keep]
    fixed = e[np.isfinite(e)]
    if not fixed.size:
        return (None, None, 0.0)
    return (float(fixed.mean()), float(np.median(fixed)), float(np.isfinite(e).mean()))


def ablation(profile: Profile, train, val, model, model_bg_only) -> list[dict]:
    """Rows: method x background, with train and validation figures."""
    base = np.asarray(profile.geometry.delays(), dtype=np.float64)
    delays = base + np.asarray(profile.echo_timing.delay_shift_samples)
    methods = [
        ("MEMG mode ToA + echo-quality shift (before)", lambda c: c.memg_toa, False, base),
        ("power-domain estimator, delays refit", lambda c: c.refined, True, delays),
        ("+ correction trained with background only", corrected(model_bg_only), True, delays),
        ("+ correction, with and without background (shipped)", corrected(model), True, delays),
    ]
    rows = []
    for has_bg in (True, False):
        for name, toa_of, timing_on, d in methods:
            row = {"method": name, "background": has_bg}
            for tag, cases in (("train", train), ("val", val)):
                sub = [c for c in cases if c.has_background == has_bg]
                z = np.array([c.truth_mm[2] for c in sub])
                err = tcd.locate_errors(profile, sub, toa_of, timing_on)
                row[f"{tag}_180"] = _stats(err, z, z <= 180)
                row[f"{tag}_220"] = _stats(err, z, z == 220)
                row[f"{tag}_toa_rms"] = tcd.inlier_rms(sub, toa_of, d)
            rows.append(row)
    return rows


def _fmt(s: tuple) -> str:
    mean, median, fix = s
    if mean is None:
        return "-"
    return f"{mean:.1f} / {median:.1f} ({fix:.1%})"


def markdown_table(rows: list[dict]) -> str:
    head = (
        "| background | method | val z<=180 mean / median (fix) | val z=220 | train z<=180 | "
        "train z=220 | ToA rms val / train (samples) |\n|---|---|---|---|---|---|---|\n"
    )
    body = "".join(
        f"| {'yes' if r['background'] else 'no'} | {r['method']} | {_fmt(r['val_180'])} | "
        f"{_fmt(r['val_220'])} | {_fmt(r['train_180'])} | {_fmt(r['train_220'])} | "
        f"{r['val_toa_rms']:.3f} / {r['train_toa_rms']:.3f} |\n"
        for r in rows
    )
    return head + body


def scoring_us(model_path: Path, n_channels: int, n: int = 2000) -> float:
    """Median microseconds for onnxruntime to score one acquisition's n_channels echoes."""
    from spiel_edge.pipeline.learned.toa_correction import load_correction

    corr = load_correction(n_channels, model_path)
    x = np.random.default_rng(0).random((n_channels, n_toa_features(n_channels)))
    times = []
    for _ in range(n):
        t0 = time.perf_counter_ns()
        corr.predict(x)
        times.append((time.perf_counter_ns() - t0) / 1e3)
    return float(np.median(times))


def write(path: Path, profile: Profile, rows: list[dict], info: dict) -> None:
    choice = "\n".join(f"| {k} | {v:.4f} |" for k, v in info["choice"].items())
    text = CARD.format(
        profile=profile.name,
        table=markdown_table(rows),
        choice=choice,
        shift=", ".join(f"{v:+.4f}" for v in info["shift"]),
        val_xy=", ".join(f"({x:g}, {y:g})" for x, y in info["val_xy"]),
        features=", ".join(f"`{n}`" for n in info["names"]),
        n_features=len(info["names"]),
        scoring=scoring_us(path.with_suffix(".onnx"), profile.geometry.n_channels),
        **{k: v for k, v in info.items() if k not in ("choice", "shift", "val_xy", "names")},
    )
    path.write_text(text)


CARD = (Path(__file__).resolve().parent / "toa_correction_card.md.in").read_text()
