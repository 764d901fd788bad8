"""Fit the DK-CH101 ranging constants on the developers' part of SToF-Chirp and validate them
leaving whole distances out.

    python -m tools.train.fit_ranging DEV_FOLDER/train [--profile PROFILE]
    python -m tools.train.fit_ranging DEV_FOLDER/train --sweep   # MEMG window x ToA estimator

DEV_FOLDER: the output of /work/shared/datasets/stof-chirp101/extract_dev.py (train/<d>/,
truth/, sensor_specs.yaml). Per frame the pipeline's envelope ToA of the first echo (the
profile's MEMG window and estimator) and the carrier phase at it. On the training distances
of each fold: the envelope ToA as one line of the time of flight (delay and range_scale), the
phase offset that puts the phase time on that line (circular mean), the wrap reference's shift
(circular mean of phase time - envelope ToA), and each timing's error std from an inner
leave-one-distance-out on the training distances alone. Scored on the left-out distance.
Prints the metrics of both timings and the constants fitted on every distance (what the
built-in profile holds).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math

import numpy as np

from spiel_edge.cli._recording_profile import recording_profile
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.ranging import CONFIDENCE_COLUMN, echo_phase, iq_refine, toa_sigma
from spiel_edge.recordings.stof_chirp import (
    find_specs,
    iter_stof_recordings,
    profile_for_specs,
    read_specs,
    sequence_folders,
    truth_mm,
)

Z95 = 1.959964
SWEEP_WINDOWS = ((5, 6), (3, 4), (4, 8), (6, 10))
SWEEP_TOA = ("mode", "mu", "half", "peak")
SWEEP_PEAK_WEIGHTS = (0.0, 0.25, 0.5, 0.75)  # with the profile's window and estimator


def load_frames(folder):
    """[(truth mm, (1, 256) I/Q frame)] of every labelled frame."""
    out = []
    for seq in sequence_folders(folder):
        truth = truth_mm(seq)
        if truth is None:
            continue
        out.extend(
            (truth, rec.frames) for rec in iter_stof_recordings(seq, True) if rec.frames is not None
        )
    return out


def frames_table(profile, frames):
    """Rows (truth mm, time of flight in samples, envelope ToA, phase at it, the echo's
    amplitude alpha, its echo confidence)."""
    env = profile.replace(ranging=dataclasses.replace(profile.ranging, timing="envelope"))
    pipe = build_pipeline(env)
    fs, c = profile.acquisition.sample_rate_hz, profile.geometry.speed_of_sound_m_s
    rows = []
    for truth, frame in frames:
        tof = 2 * truth / 1e3 / c * fs
        res = pipe.process(frame)
        k = res.matched[0]
        if k is None:
            rows.append((truth, tof, np.nan, np.nan, np.nan, np.nan))
            continue
        t = float(res.envelope_toa[0])
        phase = echo_phase(t, frame[0, 1::2], frame[0, 0::2])
        alpha, confidence = res.features[0, k, 0], res.features[0, k, CONFIDENCE_COLUMN]
        rows.append((truth, tof, t, np.nan if phase is None else phase, alpha, confidence))
    return np.array(rows, dtype=np.float64)


def fit(table, f):
    """(delay, slope, offset_rad, shift): ToA = delay + slope x ToF; the phase offset; the
    wrap reference's shift (samples)."""
    ok = np.isfinite(table[:, 2]) & np.isfinite(table[:, 3])
    tof, t, phase = table[ok, 1], table[ok, 2], table[ok, 3]
    slope, delay = np.polyfit(tof, t, 1)
    line = delay + slope * tof
    offset = float(np.angle(np.mean(np.exp(1j * (phase + 2 * math.pi * f * line)))))
    t_phase = (offset - phase) / (2 * math.pi * f)
    shift = float(np.angle(np.mean(np.exp(2j * math.pi * f * (t_phase - t)))) / (2 * math.pi * f))
    return float(delay), float(slope), offset, shift


def apply(table, f, constants, timing, margin, mmps):
    """Range errors (mm) and the timing each row used."""
    delay, slope, offset, shift = constants
    errors, kinds = [], []
    for truth, _tof, t, phase, _alpha, _confidence in table:
        if not math.isfinite(t):
            errors.append(np.nan)
            kinds.append("none")
            continue
        toa, kind = t, "envelope"
        if timing == "iq" and math.isfinite(phase):
            # the pipeline's iq_refine on a constant series holding the measured phase
            n = int(t) + 2
            i, q = np.full(n, math.cos(phase)), np.full(n, math.sin(phase))
            got = iq_refine(t, i, q, f, offset, (-shift, 0.0), margin)
            if got is not None:
                toa, kind = got, "iq"
        errors.append((toa - delay) / slope * mmps / 2 - truth)
        kinds.append(kind)
    return np.array(errors), np.array(kinds)


def metrics(table, errors, kinds, sigma_mm):
    ok = np.isfinite(errors)
    e = errors[ok]
    stds = [np.std(errors[ok & (table[:, 0] == d)]) for d in np.unique(table[:, 0])]
    return {
        "frames": int(len(errors)),
        "with_range": round(float(ok.mean()), 4),
        "mae_mm": round(float(np.abs(e).mean()), 4),
        "rmse_mm": round(float(np.sqrt((e**2).mean())), 4),
        "rms_std_mm": round(float(np.sqrt(np.mean(np.square(stds)))), 4),
        "over_1mm": round(float(np.mean(np.abs(e) > 1.0)), 4),
        "iq_share": round(float(np.mean(kinds[ok] == "iq")), 4),
        "coverage95": round(float(np.mean(np.abs(e) <= Z95 * sigma_mm[ok])), 4),
    }


# the error model's grid: sqrt(a^2 + (b / alpha)^2 + (d (1 - confidence))^2) samples
GRID_A = np.linspace(0.01, 0.3, 59)
GRID_B = np.linspace(0.0, 200.0, 41)
GRID_D = np.linspace(0.0, 4.0, 21)


def fit_error_model(errors_samples, alpha, confidence, per_target: bool) -> tuple:
    """[a, b, 0, d] of the profile's error model by maximum (Gaussian) likelihood of
    held-out errors (samples); per_target False: [a, 0, 0, 0], a their rms."""
    ok = np.isfinite(errors_samples)
    e2, alpha, miss = errors_samples[ok] ** 2, alpha[ok], np.clip(1.0 - confidence[ok], 0, 1)
    if not per_target:
        return (float(np.sqrt(e2.mean())), 0.0, 0.0, 0.0)
    best, best_ll = None, -np.inf
    inv_alpha2, miss2 = 1.0 / alpha**2, miss**2
    for a in GRID_A:
        for b in GRID_B:
            base = a * a + b * b * inv_alpha2
            var = base[None, :] + (GRID_D**2)[:, None] * miss2[None, :]
            ll = -(0.5 * np.log(var) + 0.5 * e2[None, :] / var).sum(axis=1)
            j = int(np.argmax(ll))
            if ll[j] > best_ll:
                best, best_ll = (float(a), float(b), 0.0, float(GRID_D[j])), ll[j]
    return best


def held_out_errors(table, f, timing, margin, mmps, slope_of):
    """Each distance's errors (samples) with constants fitted on the others."""
    out = np.full(len(table), np.nan)
    for d in np.unique(table[:, 0]):
        test = table[:, 0] == d
        constants = fit(table[~test], f)
        e, _ = apply(table[test], f, constants, timing, margin, mmps)
        out[test] = e * 2 / mmps * slope_of(constants)
    return out


def score_fold(table, d, f, timing, margin, mmps, per_target):
    """The left-out distance d: its rows, errors (mm), timings and interval stds (mm), every
    constant and the error model fitted on the other distances only."""
    train, test = table[table[:, 0] != d], table[table[:, 0] == d]
    inner = held_out_errors(train, f, timing, margin, mmps, lambda c: c[1])
    model = fit_error_model(inner, train[:, 4], train[:, 5], per_target)
    constants = fit(train, f)
    e, k = apply(test, f, constants, timing, margin, mmps)
    to_mm = mmps / constants[1] / 2
    sig = [toa_sigma(model, a, 0.0, c) * to_mm for a, c in zip(test[:, 4], test[:, 5], strict=True)]
    return test, e, k, np.array(sig)


def summarize_folds(folds):
    table = np.vstack([t for t, _, _, _ in folds])
    errors = np.concatenate([e for _, e, _, _ in folds])
    sigma = np.concatenate([s for _, _, _, s in folds])
    out = metrics(table, errors, kinds=np.concatenate([k for _, _, k, _ in folds]), sigma_mm=sigma)
    per = [
        np.mean(np.abs(errors[table[:, 0] == d]) <= Z95 * sigma[table[:, 0] == d])
        for d in np.unique(table[:, 0])
    ]
    out["coverage95_worst_distance"] = round(float(min(per)), 4)
    return out


def lodo(table, f, timing, margin, mmps, per_target=False):
    """Leave one distance out; each fold's interval std from the error model fitted on an
    inner leave-one-distance-out over its training distances alone."""
    distances = np.unique(table[:, 0])
    return summarize_folds(
        [score_fold(table, d, f, timing, margin, mmps, per_target) for d in distances]
    )


def nested_peak_weight(tables, f, margin, mmps):
    """Leave one distance out with ``peak_weight`` chosen inside each fold: the weight whose
    inner leave-one-distance-out over the six training distances gives the smallest spread
    with < 1 % of frames one wrap off; (metrics, the weight each fold chose)."""
    first = next(iter(tables.values()))
    folds, chosen = [], []
    for d in np.unique(first[:, 0]):
        best = None
        for weight, table in tables.items():
            train = table[table[:, 0] != d]
            e = held_out_errors(train, f, "iq", margin, mmps, lambda c: 1.0) * mmps / 2
            spread = np.sqrt(
                np.mean([np.nanvar(e[train[:, 0] == d2]) for d2 in np.unique(train[:, 0])])
            )
            wrong = np.nanmean(np.abs(e) > 1.0)
            score = (wrong >= 0.01, spread)
            if best is None or score < best[0]:
                best = (score, weight)
        chosen.append(best[1])
        folds.append(score_fold(tables[best[1]], d, f, "iq", margin, mmps, True))
    return summarize_folds(folds), chosen


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("folder")
    ap.add_argument("--profile", default=None, help="default: the one sensor_specs.yaml names")
    ap.add_argument("--margin", type=float, default=0.0, help="iq_wrap_margin")
    ap.add_argument(
        "--sweep", action="store_true", help="envelope timing per MEMG window and ToA estimator"
    )
    ap.add_argument(
        "--nested", action="store_true", help="I/Q with peak_weight chosen inside each fold"
    )
    args = ap.parse_args(argv)
    if args.profile is None:  # the board of the specs, at their temperature
        profile = profile_for_specs(read_specs(find_specs(args.folder)))
    else:
        profile = recording_profile(args.folder, "stof-chirp", args.profile, None, param="")
    f = profile.acquisition.carrier_hz / profile.acquisition.sample_rate_hz
    mmps = profile.mm_per_sample
    frames = load_frames(args.folder)
    if args.sweep:
        for before, after in SWEEP_WINDOWS:
            for toa in SWEEP_TOA:
                memg = dataclasses.replace(
                    profile.memg, window_before=before, window_after=after, toa=toa
                )
                table = frames_table(profile.replace(memg=memg), frames)
                m = lodo(table, f, "envelope", 0.5, mmps)
                print(json.dumps({"window": [before, after], "toa": toa, **m}), flush=True)
        for weight in SWEEP_PEAK_WEIGHTS:
            ranging = dataclasses.replace(profile.ranging, peak_weight=weight)
            table = frames_table(profile.replace(ranging=ranging), frames)
            for timing in ("envelope", "iq"):
                m = lodo(table, f, timing, args.margin if timing == "iq" else 0.5, mmps)
                print(json.dumps({"peak_weight": weight, "timing": timing, **m}), flush=True)
        return 0
    if args.nested:
        tables = {}
        for weight in SWEEP_PEAK_WEIGHTS:
            ranging = dataclasses.replace(profile.ranging, peak_weight=weight)
            tables[weight] = frames_table(profile.replace(ranging=ranging), frames)
        metrics_, chosen = nested_peak_weight(tables, f, args.margin, mmps)
        print(json.dumps({"iq, peak_weight chosen in each fold": metrics_, "chosen": chosen}))
        return 0
    table = frames_table(profile, frames)
    out = {t: lodo(table, f, t, args.margin, mmps) for t in ("envelope", "iq")}
    out["envelope, per-target error model"] = lodo(table, f, "envelope", 0.5, mmps, True)
    out["iq, per-target error model"] = lodo(table, f, "iq", args.margin, mmps, True)
    delay, slope, offset, shift = fit(table, f)
    models = {}
    for timing, margin in (("envelope", 0.5), ("iq", args.margin)):
        held = held_out_errors(table, f, timing, margin, mmps, lambda c: c[1])
        model = fit_error_model(held, table[:, 4], table[:, 5], True)
        models[timing] = [round(v, 4) for v in model]
    out["profile_constants"] = {
        "geometry.delay_samples": round(delay, 4),
        "ranging.range_scale": round(1.0 / slope, 6),
        "ranging.iq_phase_offset_rad": round(offset, 4),
        "ranging.iq_drift_samples": [round(-shift, 4), 0.0],
        "ranging.envelope_sigma": models["envelope"],
        "ranging.iq_sigma": models["iq"],
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
