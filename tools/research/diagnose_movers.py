"""Where the pipeline loses the virtual board's movers (docs/tracking.md, "Why movers are
missed").

    python -m tools.research.diagnose_movers [--movers 3] [--seed 0] [--acquisitions 300]

Per acquisition and true target: on how many channels an echo was detected within
``--tol`` samples of its true time of arrival, whether another target's echo lies within
``--merge`` samples of it on that channel (two echoes that close merge into one envelope
peak), and whether a target of the acquisition lies within 40 mm. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from spiel_edge.link.sim_options import SimOptions
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.sim.scenes import build_scene
from tools.bench.track_movers import add_toa_correction
from tools.bench.track_scene import match


def diagnose(
    movers: int,
    seed: int,
    acquisitions: int,
    max_targets: int,
    tol: float,
    merge: float,
    toa_correction: str | None = "none",
):
    profile = load_profile("spiel-icra23")
    pipeline = build_pipeline(profile, None, toa_correction)
    pipeline.set_max_targets(max_targets)
    scene = build_scene(SimOptions.from_url(f"sim://?scene=model&movers={movers}&seed={seed}"))
    rows = []  # per (acquisition, target): detected channels, merged channels, found
    for k in range(acquisitions):
        frame = scene.frame(k, profile.acquisition.n_samples, k / 50.0)
        result = pipeline.process(frame.samples.astype(float), frame.background.astype(float))
        truth = frame.truth_targets_mm
        toas = np.array([scene.arrival_samples(p) for p in truth])  # (K, channels)
        positions = np.array([t.position_mm for t in result.targets]).reshape(-1, 3)
        found = match(truth, positions) >= 0
        for i in range(len(truth)):
            detected = sum(
                any(abs(e - toas[i, n]) <= tol for e in result.echoes[n])
                for n in range(toas.shape[1])
            )
            others = np.delete(toas, i, axis=0)
            merged = int(np.sum(np.any(np.abs(others - toas[i]) <= merge, axis=0)))
            rows.append((detected, merged, bool(found[i])))
    arr = np.array(rows, dtype=float)
    det, mer, fnd = arr[:, 0], arr[:, 1], arr[:, 2].astype(bool)
    channels = toas.shape[1]
    out = {"acquisition_targets": len(arr), "found": round(float(fnd.mean()), 3)}
    for label, mask in (
        ("all channels detected, none merged", (det == channels) & (mer == 0)),
        ("all channels detected, some merged", (det == channels) & (mer > 0)),
        ("a channel missing, none merged", (det < channels) & (mer == 0)),
        ("a channel missing, some merged", (det < channels) & (mer > 0)),
    ):
        out[label] = {"share": round(float(mask.mean()), 3), "found": _rate(fnd[mask])}
    return out


def _rate(values: np.ndarray) -> float | None:
    return round(float(values.mean()), 3) if len(values) else None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--movers", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--acquisitions", type=int, default=300)
    add_toa_correction(parser)
    parser.add_argument("--max-targets", type=int, default=4)
    parser.add_argument("--tol", type=float, default=1.0, help="samples")
    parser.add_argument("--merge", type=float, default=2.0, help="samples")
    args = parser.parse_args(argv)
    out = diagnose(
        args.movers,
        args.seed,
        args.acquisitions,
        args.max_targets,
        args.tol,
        args.merge,
        args.toa_correction,
    )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
