"""Four CH101 with I/Q (built-in ``ch101-quad-iq``) on the virtual board's echo model: 3-D
error and CPU per acquisition timed by the carrier phase, against the same pairs' magnitude
(the staged envelope path, and the compiled one of the envelope twin profile).

    python -m tools.bench.iq3d_virtual [--n 200] [--repeat 3]

Targets uniform in x, y in [-60, 60] mm, z in [90, 200] mm, noise 5 counts on the magnitude
(the model's phase is an exact delay: an idealised phase, so the I/Q error is a floor, not a
CH101's). Prints JSON: per path the share with a position, median / p95 3-D error (mm), the
timings the records give, and the best-of-``repeat`` CPU microseconds per acquisition.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections import Counter

import numpy as np

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.sim.scenes import EchoModelScene


def acquisitions(profile, n: int, seed: int = 0):
    """(pairs (channels, 2 x samples) q, i interleaved, background envelope, truth) x n."""
    acq = profile.acquisition
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        truth = np.array([rng.uniform(-60, 60), rng.uniform(-60, 60), rng.uniform(90, 200)])
        scene = EchoModelScene(
            profile.geometry,
            sample_rate_hz=acq.sample_rate_hz,
            n_samples=acq.n_samples,
            targets_mm=truth[None, :],
            noise=5.0,
            seed=k,
            carrier_hz=acq.carrier_hz,
        )
        frame = scene.frame(0, acq.n_samples, 0.0, iq=True)
        pairs = frame.iq.reshape(frame.iq.shape[0], -1).astype(np.float64)
        out.append((pairs, scene.background(acq.n_samples), truth))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    profile = load_profile("ch101-quad-iq")
    by_envelope = dataclasses.replace(profile.ranging, timing="envelope")
    twin = profile.replace(
        acquisition=dataclasses.replace(profile.acquisition, signal="envelope"),
        ranging=by_envelope,
    )
    paths = {
        "iq_phase": (build_pipeline(profile), False),
        "iq_magnitude_staged": (build_pipeline(profile.replace(ranging=by_envelope)), False),
        "envelope_compiled": (build_pipeline(twin), True),
    }
    data = acquisitions(profile, args.n)
    out = {"acquisitions": args.n}
    for name, (pipe, magnitude) in paths.items():
        frames = [(np.hypot(p[:, 0::2], p[:, 1::2]) if magnitude else p, b) for p, b, _ in data]
        results = [pipe.process(f, b) for f, b in frames]
        errors = np.array(
            [
                np.nan if r.position_mm is None else np.linalg.norm(r.position_mm - t)
                for r, (_, _, t) in zip(results, data, strict=True)
            ]
        )
        cpu = []
        for _ in range(args.repeat):
            start = time.process_time()
            for f, b in frames:
                pipe.process(f, b)
            cpu.append((time.process_time() - start) / len(frames) * 1e6)
        out[name] = {
            "with_position": round(float(np.isfinite(errors).mean()), 4),
            "median_error_mm": round(float(np.nanmedian(errors)), 3),
            "p95_error_mm": round(float(np.nanpercentile(errors, 95)), 3),
            "timing": dict(Counter(str(r.record().get("timing")) for r in results)),
            "cpu_us": round(min(cpu)),
        }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
