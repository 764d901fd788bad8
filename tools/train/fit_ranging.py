"""Fit the DK-CH101 ranging constants on the developers' part of SToF-Chirp and validate them
leaving whole distances out.

    python -m tools.train.fit_ranging DEV_FOLDER/train [--profile dk-ch101-gpr-sr-narrow]
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

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.ranging import echo_phase, iq_refine
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.profile.recording_profile import recording_profile
from spiel_edge.recordings.stof_chirp import iter_stof_recordings, sequence_folders, truth_mm

Z95 = 1.959964
SWEEP_WINDOWS = ((5, 6), (3, 4), (4, 8), (6, 10))
SWEEP_TOA = ("mode", "mu", "half", "peak")


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
    """Rows (truth mm, time of flight in samples, envelope ToA, phase at it, nan)."""
    env = profile.replace(ranging=dataclasses.replace(profile.ranging, timing="envelope"))
    pipe = build_pipeline(env)
    fs, c = profile.acquisition.sample_rate_hz, profile.geometry.speed_of_sound_m_s
    rows = []
    for truth, frame in frames:
        tof = 2 * truth / 1e3 / c * fs
        res = pipe.process(frame)
        k = res.matched[0]
        if k is None:
            rows.append((truth, tof, np.nan, np.nan))
            continue
        t = float(res.features[0, k, TOA_COLUMN])
        phase = echo_phase(t, frame[0, 1::2], frame[0, 0::2])
        rows.append((truth, tof, t, np.nan if phase is None else phase))
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
    for truth, _tof, t, phase in table:
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


def lodo(table, f, timing, margin, mmps):
    """Leave one distance out; the std of each fold's intervals from an inner
    leave-one-distance-out on its training distances."""
    rows, errs, kinds, sigmas = [], [], [], []
    for d in np.unique(table[:, 0]):
        train, test = table[table[:, 0] != d], table[table[:, 0] == d]
        inner = []
        for d2 in np.unique(train[:, 0]):
            tr2, te2 = train[train[:, 0] != d2], train[train[:, 0] == d2]
            inner.append(apply(te2, f, fit(tr2, f), timing, margin, mmps)[0])
        inner = np.concatenate(inner)
        sigma = float(np.sqrt(np.nanmean(inner**2)))
        e, k = apply(test, f, fit(train, f), timing, margin, mmps)
        rows.append(test)
        errs.append(e)
        kinds.append(k)
        sigmas.append(np.full(len(e), sigma))
    table = np.vstack(rows)
    return metrics(table, np.concatenate(errs), np.concatenate(kinds), np.concatenate(sigmas))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("folder")
    ap.add_argument("--profile", default="dk-ch101-gpr-sr-narrow")
    ap.add_argument("--margin", type=float, default=0.0, help="iq_wrap_margin")
    ap.add_argument(
        "--sweep", action="store_true", help="envelope timing per MEMG window and ToA estimator"
    )
    args = ap.parse_args(argv)
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
        return 0
    table = frames_table(profile, frames)
    out = {t: lodo(table, f, t, args.margin, mmps) for t in ("envelope", "iq")}
    delay, slope, offset, shift = fit(table, f)
    sig = {}
    for timing in ("envelope", "iq"):
        e, k = apply(table, f, (delay, slope, offset, shift), timing, args.margin, mmps)
        inner = []
        for d in np.unique(table[:, 0]):
            tr, te = table[table[:, 0] != d], table[table[:, 0] == d]
            inner.append(apply(te, f, fit(tr, f), timing, args.margin, mmps)[0])
        rms_mm = float(np.sqrt(np.nanmean(np.concatenate(inner) ** 2)))
        sig[timing] = round(rms_mm * 2 / (mmps / slope), 4)  # samples
    out["profile_constants"] = {
        "geometry.delay_samples": round(delay, 4),
        "ranging.range_scale": round(1.0 / slope, 6),
        "ranging.iq_phase_offset_rad": round(offset, 4),
        "ranging.iq_drift_samples": [round(-shift, 4), 0.0],
        "ranging.envelope_sigma[0]": sig["envelope"],
        "ranging.iq_sigma[0]": sig["iq"],
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
