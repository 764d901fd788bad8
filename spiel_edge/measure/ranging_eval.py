"""Range accuracy of a one-transducer board on labelled SToF-Chirp sequences: per labelled
distance the error of every frame's ``range_mm``, and the share of truths inside the 95 %
interval its variance states (``range_mm`` +- 1.96 sqrt(range_var_mm2))."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from spiel_edge.recordings.stof_chirp import iter_stof_recordings, sequence_folders, truth_mm

Z95 = 1.959964


def range_errors(pipeline, folder: str | Path, limits=None) -> dict[float, list[dict]]:
    """truth (mm) -> per frame {error_mm, std_mm, timing} (error None: no range)."""
    iq = pipeline.profile.acquisition.signal == "iq"
    out: dict[float, list[dict]] = {}
    for seq in sequence_folders(folder):
        truth = truth_mm(seq)
        if truth is None:
            continue
        rows = out.setdefault(truth, [])
        for rec in iter_stof_recordings(seq, iq, limits):
            if rec.frames is None:
                rows.append({"error_mm": None, "std_mm": None, "timing": None})
                continue
            r = pipeline.process(rec.frames).record()
            if r.get("range_mm") is None:
                rows.append({"error_mm": None, "std_mm": None, "timing": None})
                continue
            std = math.sqrt(r["range_var_mm2"]) if r.get("range_var_mm2") is not None else None
            rows.append({"error_mm": r["range_mm"] - truth, "std_mm": std, "timing": r["timing"]})
    return out


def summarize(errors: dict[float, list[dict]]) -> dict:
    """MAE, RMSE, per-distance mean and std, the rms of the per-distance stds, the share of
    frames more than 1 mm off, the share with a range, 95 % coverage, timings used."""
    all_rows = [row for rows in errors.values() for row in rows]
    ok = [row for row in all_rows if row["error_mm"] is not None]
    if not ok:
        return {"frames": len(all_rows), "with_range": 0.0}
    e = np.array([row["error_mm"] for row in ok])
    stds = np.array([row["std_mm"] if row["std_mm"] is not None else np.nan for row in ok])
    per = {}
    for truth, rows in sorted(errors.items()):
        d = np.array([row["error_mm"] for row in rows if row["error_mm"] is not None])
        if d.size:
            per[f"{truth:g}"] = {
                "frames": len(rows),
                "mean_mm": round(float(d.mean()), 4),
                "std_mm": round(float(d.std()), 4),
                "mae_mm": round(float(np.abs(d).mean()), 4),
            }
    timings: dict[str, int] = {}
    for row in ok:
        timings[row["timing"]] = timings.get(row["timing"], 0) + 1
    covered = np.abs(e) <= Z95 * stds
    return {
        "frames": len(all_rows),
        "with_range": round(len(ok) / len(all_rows), 4),
        "mae_mm": round(float(np.abs(e).mean()), 4),
        "rmse_mm": round(float(np.sqrt((e**2).mean())), 4),
        "rms_std_mm": round(float(np.sqrt(np.mean([v["std_mm"] ** 2 for v in per.values()]))), 4),
        "over_1mm": round(float(np.mean(np.abs(e) > 1.0)), 4),
        "coverage95": round(float(np.mean(covered[np.isfinite(stds)])), 4)
        if np.isfinite(stds).any()
        else None,
        "timing": timings,
        "by_distance": per,
    }
