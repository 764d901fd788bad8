"""Evidence for the README: calibrate on the train positions of the shared recordings, then
the 3-D error on the validation positions (unseen x, y) with nominal vs calibrated geometry.

    python -m tools.bench.calibration_evidence ../shared/datasets/spiel-icra23 [--seeds 5]

The z = 90 mm frames are excluded (mislabelled, see the dataset README).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from spiel_edge.calibrate import calibrate_frames, load_recordings
from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.measure.evaluate import evaluate_folder, split_by_position
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import Profile, load_profile
from spiel_edge.recordings.spiel_csv import frame_files


def val_error(profile: Profile, folder: Path, bg: Path, val: set) -> dict:
    ev = evaluate_folder(
        build_pipeline(profile), folder, bg, positions=val, exclude_z=EXCLUDED_Z_MM
    )
    s = ev.summary()
    return {k: s[k] for k in ("frames", "fix_rate", "mean_mm", "median_mm", "p95_mm")}


def perturbed(profile: Profile, seed: int, mm: float = 5.0) -> Profile:
    """Each receiver moved ``mm`` in a random direction, delays zeroed."""
    g = profile.geometry
    rng = np.random.default_rng(seed)
    d = rng.normal(size=g.channels_mm.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[np.linalg.norm(g.channels_mm - g.emitter_mm, axis=1) < 1.0] = 0.0  # the emitter's own channel
    g2 = dataclasses.replace(
        g, channels_mm=g.channels_mm + mm * d, delay_samples=np.zeros(g.n_channels)
    )
    return profile.replace(geometry=g2)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument(
        "--fix", default="", help="comma-separated parameters to keep fixed (default: none)"
    )
    args = ap.parse_args()
    folder, bg = args.dataset / "train_val", args.dataset / "train_val_bg"
    train, val = split_by_position(p.name for p in frame_files(folder))
    fix = {f for f in args.fix.split(",") if f}
    data = load_recordings(folder, bg, positions=train, exclude_z=EXCLUDED_Z_MM)
    hand = load_profile("spiel-icra23")
    nominal = hand.replace(
        geometry=dataclasses.replace(
            hand.geometry, delay_samples=np.zeros(hand.geometry.n_channels)
        )
    )
    out: dict = {"calibration_frames": len(data.names), "fix": sorted(fix)}
    out["hand_tuned"] = val_error(hand, folder, bg, val)
    out["nominal_no_delays"] = val_error(nominal, folder, bg, val)
    t0 = time.perf_counter()
    cal = calibrate_frames(hand, data.frames, data.backgrounds, data.truth_mm, fix=fix)
    out["calibrate_seconds"] = round(time.perf_counter() - t0, 2)
    out["hand_tuned_calibrated"] = val_error(hand.replace(geometry=cal.geometry), folder, bg, val)
    out["hand_tuned_calibrated_geometry"] = {
        "channels_mm": cal.geometry.channels_mm.round(2).tolist(),
        "delay_samples": cal.geometry.delays().round(3).tolist(),
        "speed_of_sound_m_s": round(cal.geometry.speed_of_sound_m_s, 2),
        "scale_samples": round(cal.result.scale, 3),
        "std": {
            n: round(float(s), 3) for n, s in zip(cal.result.names, cal.result.std, strict=True)
        },
    }
    runs = []
    for seed in range(args.seeds):
        start = perturbed(hand, seed)
        c = calibrate_frames(start, data.frames, data.backgrounds, data.truth_mm, fix=fix)
        runs.append(
            {
                "seed": seed,
                "perturbed": val_error(start, folder, bg, val),
                "calibrated": val_error(hand.replace(geometry=c.geometry), folder, bg, val),
            }
        )
    out["perturbed_runs"] = runs
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
