"""Fit the DK-CH101 ranging constants on the developers' part of SToF-Chirp and validate them
leaving whole distances out.

    python -m tools.train.fit_ranging DEV_FOLDER [--profile dk-ch101-gpr-sr-narrow] [--json]

DEV_FOLDER: the output of /work/shared/datasets/stof-chirp101/extract_dev.py (train/<d>/,
truth/, sensor_specs.yaml). Per frame the pipeline's envelope timing (MEMG mode of the first
echo) and the carrier phase at it; then, on the training distances of each fold: the delay
(mean envelope ToA - time of flight), the phase offset (circular mean, so the phase time sits
on the envelope's scale), the envelope drift a + b t (least squares) and the error model of
each timing (std of the fold's residuals). Prints the leave-one-distance-out metrics and the
constants fitted on every distance (what the built-in profile holds).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math

import numpy as np

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.ranging import echo_phase, iq_refine
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.profile.recording_profile import recording_profile
from spiel_edge.recordings.stof_chirp import iter_stof_recordings, sequence_folders, truth_mm

Z95 = 1.959964


def frames_table(folder, profile_name):
    """Per frame: distance (mm), ToF (samples), envelope ToA, phase, alpha; and the profile."""
    base = recording_profile(folder, "stof-chirp", profile_name, None, param="")
    env = base.replace(ranging=dataclasses.replace(base.ranging, timing="envelope"))
    pipe = build_pipeline(env)
    fs = base.acquisition.sample_rate_hz
    c = base.geometry.speed_of_sound_m_s
    rows = []
    for seq in sequence_folders(folder):
        truth = truth_mm(seq)
        if truth is None:
            continue
        for rec in iter_stof_recordings(seq, True):
            if rec.frames is None:
                continue
            res = pipe.process(rec.frames)
            k = res.matched[0]
            if k is None:
                rows.append((truth, 2 * truth / 1e3 / c * fs, np.nan, np.nan, np.nan))
                continue
            t = float(res.features[0, k, TOA_COLUMN])
            q, i = rec.frames[0, 0::2], rec.frames[0, 1::2]
            phase = echo_phase(t, i, q)
            rows.append((truth, 2 * truth / 1e3 / c * fs, t, phase, float(res.features[0, k, 0])))
    return base, np.array(rows, dtype=np.float64)


def fit(table, f):
    """delay, offset_rad, drift (a, b), envelope std, iq std (samples) from rows."""
    ok = np.isfinite(table[:, 2])
    tof, t, phase = table[ok, 1], table[ok, 2], table[ok, 3]
    delay = float(np.mean(t - tof))
    target = tof + delay  # where the ToA should be
    offset = float(np.angle(np.mean(np.exp(1j * (phase + 2 * math.pi * f * target)))))
    resid = t - target
    b, a = np.polyfit(t, resid, 1)
    env_std = float(np.std(resid))
    return delay, offset, (float(a), float(b)), env_std


def apply(table, f, delay, offset, drift, margin, mmps):
    """Range errors (mm) and the timing of each row with these constants."""
    errors, kinds = [], []
    for truth, tof, t, phase, _alpha in table:
        if not math.isfinite(t):
            errors.append(np.nan)
            kinds.append("none")
            continue
        t_iq = None
        if math.isfinite(phase) and margin < 0.5:  # margin >= 0.5: envelope timing only
            wrap = 1.0 / f
            ref = t - (drift[0] + drift[1] * t)
            t_phase = (offset - phase) / (2 * math.pi * f)
            step = math.remainder(t_phase - ref, wrap)
            t_iq = None if abs(step) > wrap * (0.5 - margin) else ref + step
        toa = t if t_iq is None else t_iq
        errors.append((toa - delay) * mmps / 2 - truth)
        kinds.append("envelope" if t_iq is None else "iq")
    return np.array(errors), np.array(kinds)


def metrics(table, errors, kinds, env_sigma_mm, iq_sigma_mm):
    ok = np.isfinite(errors)
    e = errors[ok]
    stds = [np.std(errors[ok & (table[:, 0] == d)]) for d in np.unique(table[:, 0])]
    sig = np.where(kinds[ok] == "iq", iq_sigma_mm, env_sigma_mm)
    return {
        "frames": int(len(errors)),
        "with_range": round(float(ok.mean()), 4),
        "mae_mm": round(float(np.abs(e).mean()), 4),
        "rmse_mm": round(float(np.sqrt((e**2).mean())), 4),
        "rms_std_mm": round(float(np.sqrt(np.mean(np.square(stds)))), 4),
        "over_1mm": round(float(np.mean(np.abs(e) > 1.0)), 4),
        "iq_share": round(float(np.mean(kinds[ok] == "iq")), 4),
        "coverage95": round(float(np.mean(np.abs(e) <= Z95 * sig)), 4),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder")
    ap.add_argument("--profile", default="dk-ch101-gpr-sr-narrow")
    ap.add_argument("--margin", type=float, default=0.0)
    ap.add_argument("--timing", choices=("iq", "envelope"), default="iq")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.timing == "envelope":
        args.margin = 0.5
    profile, table = frames_table(args.folder, args.profile)
    if args.timing == "envelope":
        table[:, 3] = np.nan
    f = profile.acquisition.carrier_hz / profile.acquisition.sample_rate_hz
    mmps = profile.mm_per_sample
    distances = np.unique(table[:, 0])
    # leave one distance out: the fold's constants, its error model from the training
    # distances' own leave-one-out residuals (positions never fitted), applied to the left-out
    all_err, all_kind, all_rows, sig_env, sig_iq = [], [], [], [], []
    for d in distances:
        train, test = table[table[:, 0] != d], table[table[:, 0] == d]
        delay, offset, drift, _ = fit(train, f)
        inner_env, inner_iq = [], []
        for d2 in np.unique(train[:, 0]):  # inner leave-one-out for the error model
            tr2, te2 = train[train[:, 0] != d2], train[train[:, 0] == d2]
            c2 = fit(tr2, f)
            e2, k2 = apply(te2, f, c2[0], c2[1], c2[2], args.margin, mmps)
            inner_env.extend(e2[k2 == "envelope"])
            inner_iq.extend(e2[k2 == "iq"])
        s_iq = float(np.sqrt(np.mean(np.square(inner_iq)))) if inner_iq else 0.1
        s_env = float(np.sqrt(np.mean(np.square(inner_env)))) if len(inner_env) > 5 else 2 * s_iq
        e, k = apply(test, f, delay, offset, drift, args.margin, mmps)
        all_err.append(e)
        all_kind.append(k)
        all_rows.append(test)
        sig_env.append(np.full(len(e), s_env))
        sig_iq.append(np.full(len(e), s_iq))
    table_lodo = np.vstack(all_rows)
    errors, kinds = np.concatenate(all_err), np.concatenate(all_kind)
    out = {
        "leave_one_distance_out": metrics(
            table_lodo, errors, kinds, np.concatenate(sig_env)[np.isfinite(errors)],
            np.concatenate(sig_iq)[np.isfinite(errors)],
        ),
    }
    delay, offset, drift, _ = fit(table, f)
    # the error model for the profile: leave-one-distance-out rms of each timing's residuals
    iq_rms = float(np.sqrt(np.nanmean(np.square(errors[kinds == "iq"])))) if (kinds == "iq").any() else math.nan
    env_rms = float(np.sqrt(np.nanmean(np.square(errors[kinds == "envelope"])))) if (kinds == "envelope").any() else math.nan
    out["profile_constants"] = {
        "delay_samples": round(delay, 4),
        "iq_phase_offset_rad": round(offset, 4),
        "iq_drift_samples": [round(drift[0], 5), round(drift[1], 6)],
        "iq_sigma_samples_from_lodo_rms": round(iq_rms * 2 / mmps, 4),
        "envelope_sigma_samples_from_lodo_rms": round(env_rms * 2 / mmps, 4),
    }
    print(json.dumps(out, indent=None if args.json else 2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
