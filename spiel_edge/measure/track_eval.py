"""Tracked vs per-acquisition error on labelled recordings (``evaluate --track``).

Each recording (one static target) is tracked in time order (runtime/track_records.py). For every
acquisition with a position, the per-acquisition error is that of the best target and the
tracked error that of its confirmed track, or of the position itself while the target is not
on a confirmed track yet (the first acquisitions of a recording): both means are over the same
acquisitions, which is what a consumer of the records would see. Without a background
capture and with ``[track] running_background_window`` > 0 the running estimate of the static
scene (runtime/static_scene.py) stands in for it, fed in the same time order;
``within_30mm_share`` is the share of acquisitions with a target within 30 mm of the truth.

``static_track_mean_mm``: the recordings hold one static target each, whose track is the
confirmed track with the most hits; per acquisition its error (or the position's while there is
none). It differs from ``tracked_mean_mm`` where the best target was left out of that track (a
target outside its gate starts a tentative track of its own and counts at its own error there),
i.e. what a consumer reading the target's track sees when one acquisition goes astray.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.recordings.spiel_csv import iter_recordings, position_key, read_truth
from spiel_edge.runtime.static_scene import RunningBackground
from spiel_edge.runtime.track_records import ResultTracker, time_ordered


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
    tracker = ResultTracker(spec or pipeline.profile.track, pipeline.profile.scene)
    running = RunningBackground.from_profile(pipeline.profile)
    skip_z = set(exclude_z)
    errors = TrackedErrors()
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
        used = running.background() if stand_in else rec.background
        result = pipeline.process(rec.frames, used)
        captured = used is not None and pipeline.profile.preprocess.background_subtraction
        tracks = tracker.update(result, item.t_s, captured)
        if stand_in:
            running.update(rec.frames, tracks)
        found.append(any(np.linalg.norm(t.position_mm - truth) <= 30.0 for t in result.targets))
        if result.position_mm is not None:
            errors.add(truth, result.position_mm, tracker.best_track(tracks), tracks)
    return {
        **errors.summary(),
        "acquisitions": len(found),
        "within_30mm_share": round(float(np.mean(found)), 4) if found else None,
        "running_background": running is not None,
    }


class TrackedErrors:
    """Per acquisition with a position: its error, the tracked one (the best target's confirmed
    track, else the position) and the static target's track's (the confirmed track with the most
    hits, else the position)."""

    def __init__(self) -> None:
        self.raw: list[float] = []
        self.tracked: list[float] = []
        self.static: list[float] = []
        self.on_track: list[tuple[float, float]] = []  # (raw, tracked) where on a track

    def add(self, truth: np.ndarray, position: np.ndarray, best_track, tracks) -> None:
        error = float(np.linalg.norm(np.asarray(position) - truth))
        self.raw.append(error)
        if best_track is None:
            self.tracked.append(error)
        else:
            tracked = float(np.linalg.norm(best_track.position_mm - truth))
            self.tracked.append(tracked)
            self.on_track.append((error, tracked))
        static = max(tracks, key=lambda t: (t.hits, -t.track_id), default=None)
        self.static.append(
            error if static is None else float(np.linalg.norm(static.position_mm - truth))
        )

    def summary(self) -> dict:
        raw = self.raw
        return {
            "fixes": len(raw),
            "per_acquisition_mean_mm": _mean(raw),
            "tracked_mean_mm": _mean(self.tracked),
            "static_track_mean_mm": _mean(self.static),
            "on_track_share": round(len(self.on_track) / len(raw), 4) if raw else None,
            "on_track": {
                "per_acquisition_mean_mm": _mean([e for e, _ in self.on_track]),
                "tracked_mean_mm": _mean([t for _, t in self.on_track]),
            },
        }


def _mean(values: list[float]) -> float | None:
    return round(float(np.mean(values)), 2) if values else None
