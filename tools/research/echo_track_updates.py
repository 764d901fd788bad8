"""Prototype, measured and not merged (docs/tracking.md, "Echo-level track updates"): confirmed
tracks that found no target in an acquisition are updated from the echoes near their predicted
arrival times (an extended Kalman update per IMM model, echo paths as measurements).

    python -m tools.research.echo_track_updates --seed S [--movers 3] [--gate 1.5] [--sigma 0.7]
        [--min-channels 3] [--off]

Prints the movers' figures (as tools/bench/track_movers.py, no learned ToA correction) and the number
of echo-level updates. It writes into the tracker's arrays from outside, as a prototype may.
"""

from __future__ import annotations

import argparse
import json
from types import SimpleNamespace

import numpy as np

from spiel_edge.link.sim_options import SimOptions
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.runtime.track_records import ResultTracker
from spiel_edge.sim.scenes import build_scene
from spiel_edge.track.layout import CONFIRMED, ID, MISSES, STATUS, model_views
from tools.bench.track_scene import MoverScore


class EchoUpdater:
    """Echo paths of one acquisition -> updates of the confirmed tracks that missed."""

    def __init__(self, profile, gate: float, sigma: float, min_channels: int):
        g = profile.geometry
        self.emitter = np.asarray(g.emitter_mm, dtype=np.float64)
        self.channels = np.asarray(g.channels_mm, dtype=np.float64)
        self.delays = np.asarray(g.delays(), dtype=np.float64)
        self.mm_per_sample = g.speed_of_sound_m_s * 1000.0 / profile.acquisition.sample_rate_hz
        self.gate, self.sigma, self.min_channels = gate, sigma, min_channels

    def toas(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted ToA per channel (samples) and its gradient in position (channels, 3)."""
        a, b = p - self.emitter, p[None, :] - self.channels
        la, lb = np.linalg.norm(a), np.linalg.norm(b, axis=1)
        grad = (a / la + b / lb[:, None]) / self.mm_per_sample
        return (la + lb) / self.mm_per_sample + self.delays, grad

    def apply(self, tracker, echoes) -> int:
        x, p, meta = tracker._x, tracker._p, tracker._meta
        xm, pm, _mu = model_views(tracker._arrays[0], x.shape[0])
        done = 0
        for s in range(x.shape[0]):
            if meta[STATUS, s] != CONFIRMED or meta[MISSES, s] == 0:
                continue
            predicted, _ = self.toas(x[s, :3])
            used, z = [], []
            for n, e in enumerate(echoes):
                e = np.asarray(e, dtype=np.float64)
                nearest = int(np.argmin(np.abs(e - predicted[n]))) if len(e) else -1
                if nearest >= 0 and abs(e[nearest] - predicted[n]) <= self.gate:
                    used.append(n)
                    z.append(e[nearest])
            if len(used) < self.min_channels:
                continue
            zs = np.array(z)
            for m in range(2):
                xm[s, m], pm[s, m] = self._update(xm[s, m], pm[s, m], used, zs)
            x[s], p[s] = self._update(x[s], p[s], used, zs)
            meta[MISSES, s] = 0
            done += 1
        return done

    def _update(self, x, p, used, z):
        toa, grad = self.toas(x[:3])
        h = np.zeros((len(used), 6))
        h[:, :3] = grad[used]
        s = h @ p @ h.T + np.eye(len(used)) * self.sigma**2
        gain = p @ h.T @ np.linalg.inv(s)
        p_new = (np.eye(6) - gain @ h) @ p
        return x + gain @ (z - toa[used]), (p_new + p_new.T) / 2


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--movers", type=int, default=3)
    parser.add_argument("--seed", type=int, default=10)
    parser.add_argument("--acquisitions", type=int, default=1000)
    parser.add_argument("--gate", type=float, default=1.5, help="samples")
    parser.add_argument("--sigma", type=float, default=0.7, help="ToA std, samples")
    parser.add_argument("--min-channels", type=int, default=3)
    parser.add_argument("--off", action="store_true", help="no echo-level updates")
    args = parser.parse_args(argv)
    profile = load_profile("spiel-icra23")
    pipeline = build_pipeline(profile, None, "none")
    pipeline.set_max_targets(4)
    url = f"sim://?scene=model&movers={args.movers}&seed={args.seed}"
    scene = build_scene(SimOptions.from_url(url))
    results = ResultTracker(profile.track)
    updater = EchoUpdater(profile, args.gate, args.sigma, args.min_channels)
    score, updates = MoverScore(), 0
    n_samples = profile.acquisition.n_samples
    for k in range(args.acquisitions):
        frame = scene.frame(k, n_samples, k / 50.0)
        result = pipeline.process(frame.samples.astype(float), frame.background.astype(float))
        results.update(result, k / 50.0)
        tracker = results.tracker
        if not args.off:
            updates += updater.apply(tracker, result.echoes)
        tracks = [  # the confirmed tracks after the echo-level updates
            SimpleNamespace(
                position_mm=tracker._x[s, :3].copy(), track_id=int(tracker._meta[ID, s])
            )
            for s in range(tracker._x.shape[0])
            if tracker._meta[STATUS, s] == CONFIRMED
        ]
        found = np.array([t.position_mm for t in results.last_targets]).reshape(-1, 3)
        score.add(k, frame.truth_targets_mm, tracks, found)
    print(json.dumps({"url": url, "echo_updates": updates, **score.summary()}))


if __name__ == "__main__":
    main()
