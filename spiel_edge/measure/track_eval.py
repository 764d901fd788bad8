"""Tracked vs per-acquisition error on labelled recordings (``evaluate --track``).

Each recording (one static target) is tracked in time order (runtime/tracking.py). For every
acquisition with a position, the per-acquisition error is that of the best target and the
tracked error that of its confirmed track, or of the position itself while the target is not
on a confirmed track yet (the first acquisitions of a recording): both means are over the same
acquisitions, which is what a consumer of the records would see. Without a background
capture and with ``[track] running_background_window`` > 0 the running estimate of the static
scene (runtime/running_background.py) stands in for it, fed in the same time order;
``within_30mm_share`` is the share of acquisitions with a target within 30 mm of the truth.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from spiel_edge.io.spiel_csv import iter_recordings, position_key, read_truth
from spiel_edge.pipeline.run import Pipeline
from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.runtime.running_background import RunningBackground
from spiel_edge.runtime.tracking import ResultTracker, time_ordered


def evaluate_tracked(
    pipeline: Pipeline,
    folder: str | Path,
    background: str | Path | None = None,
    *,
    positions: set | None = None,
    exclude_z: Iterable[float] = (),
    max_z: float | None = None,
    spec: TrackSpec | None = None,
) -> dict:
    tracker = ResultTracker(spec or pipeline.profile.track)
    running = RunningBackground.from_profile(pipeline.profile)
    skip_z = set(exclude_z)
    raw, tracked, on_track, raw_on_track = [], [], [], []
    found = []  # per acquisition: a target within 30 mm
    for item in time_ordered(iter_recordings(folder, background)):
        rec = item.recording
        key = position_key(rec.source)
        if positions is not None and (key is None or key[:2] not in positions):
            continue
        truth = read_truth(Path(folder) / rec.source)
        if truth is None or float(truth[2]) in skip_z or rec.error is not None:
            continue
        if max_z is not None and truth[2] > max_z:
            continue
        if item.new_run:
            tracker.reset()
        stand_in = running is not None and rec.background is None
        result = pipeline.process(rec.frames, running.background() if stand_in else rec.background)
        tracks = tracker.update(result, item.t_s)
        if stand_in:
            running.update(rec.frames, tracks)
        track = tracker.best_track(tracks)
        found.append(any(np.linalg.norm(t.position_mm - truth) <= 30.0 for t in result.targets))
        if result.position_mm is None:
            continue
        error = float(np.linalg.norm(result.position_mm - truth))
        raw.append(error)
        if track is None:
            tracked.append(error)
            continue
        tracked_error = float(np.linalg.norm(track.position_mm - truth))
        tracked.append(tracked_error)
        on_track.append(tracked_error)
        raw_on_track.append(error)
    return {
        "fixes": len(raw),
        "per_acquisition_mean_mm": _mean(raw),
        "tracked_mean_mm": _mean(tracked),
        "on_track_share": round(len(on_track) / len(raw), 4) if raw else None,
        "acquisitions": len(found),
        "within_30mm_share": round(float(np.mean(found)), 4) if found else None,
        "running_background": running is not None,
        "on_track": {
            "per_acquisition_mean_mm": _mean(raw_on_track),
            "tracked_mean_mm": _mean(on_track),
        },
    }


def _mean(values: list[float]) -> float | None:
    return round(float(np.mean(values)), 2) if values else None
