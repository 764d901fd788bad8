"""Tracker speed for ``spiel-edge bench``: microseconds per ``Tracker.update`` with 8
confirmed tracks and 8 targets per acquisition (the issue's budget: 20 us)."""

from __future__ import annotations

import time

import numpy as np

from spiel_edge.pipeline.staged import Target
from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.track import Tracker

N_TRACKS = 8


def time_tracker(acquisitions: int = 2000, n_tracks: int = N_TRACKS, seed: int = 0) -> dict:
    """Median and p95 wall-clock us per update (targets built beforehand) and the median of
    the thread's CPU time, after 50 warm-up updates."""
    rng = np.random.default_rng(seed)
    center = np.c_[rng.uniform(-150, 150, (n_tracks, 2)), rng.uniform(100, 400, n_tracks)]
    swing = rng.uniform(20, 60, (n_tracks, 3))  # smooth back-and-forth motion
    cov = np.diag([40.0, 40.0, 25.0])
    period = 0.02
    batches = [
        [
            Target(p + rng.normal(0, 4, 3), cov, 1.0, [], 1.0)
            for p in center + swing * np.sin(2.0 * k * period)
        ]
        for k in range(acquisitions + 50)
    ]
    tracker = Tracker(TrackSpec(max_tracks=16))
    for k in range(50):
        tracker.update(batches[k], k * period)
    wall = np.empty(acquisitions)
    cpu = np.empty(acquisitions)
    counts = np.empty(acquisitions, dtype=np.int64)
    for k in range(50, acquisitions + 50):
        targets = batches[k]
        c0, t0 = time.thread_time_ns(), time.perf_counter_ns()
        tracks = tracker.update(targets, k * period)
        wall[k - 50] = (time.perf_counter_ns() - t0) / 1e3
        cpu[k - 50] = (time.thread_time_ns() - c0) / 1e3
        counts[k - 50] = len(tracks)
    return {
        "tracks_median": int(np.median(counts)),
        "median_us": round(float(np.median(wall)), 2),
        "p95_us": round(float(np.percentile(wall, 95)), 2),
        # this thread's CPU time: the wall time less the time other processes took the core
        "cpu_median_us": round(float(np.median(cpu)), 2),
    }
