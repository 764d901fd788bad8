"""Tracking in the run loop and in replays: results -> tracker -> ``tracks`` in the records.

Live, the time is the board's clock (``device_time_us``), so a board restart (its clock going
back) restarts the tracker. Recordings carry no clock: spiel-csv frames of one recording
(``<x>mm_<y>mm_<z>mm_<session>_<index>_frames.csv``) are consecutive acquisitions
``NOMINAL_PERIOD_S`` apart, in index order, and each recording starts a fresh tracker run;
an MCAP recording is one run in its recorded order.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from spiel_edge.pipeline.staged import Result, Target
from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.recordings.spiel_csv import Recording
from spiel_edge.runtime.replay import Replayed, replay
from spiel_edge.runtime.running_background import RunningBackground
from spiel_edge.track import Track, Tracker

NOMINAL_PERIOD_S = 0.02  # between recorded acquisitions (50 Hz, `run --rate`'s default)
_CSV_NAME = re.compile(r"^(?P<run>.+)_(?P<index>\d+)_frames\.csv$")
_MCAP_NAME = re.compile(r"^(?P<run>.+)#(?P<index>\d+)$")


def targets_of(result: Result) -> list[Target]:
    """The result's targets. A result with a position but no target list (a pipeline without
    the scene stage) gives one target without covariance: the tracker then assumes
    ``[track] fallback_sigma_mm``. That stand-in is not added to the record."""
    if result.targets or result.position_mm is None:
        return result.targets
    return [
        Target(
            result.position_mm,
            np.full((3, 3), np.nan),
            result.residual_mm or 0.0,
            list(result.matched),
            0.0,
        )
    ]


class ResultTracker:
    """A Tracker fed with pipeline results; keeps each result's targets' ``track_id``."""

    def __init__(self, spec: TrackSpec):
        self.tracker = Tracker(spec)
        self.tracker.update([], 0.0)  # compile (or load) the kernels before the stream starts
        self.tracker.reset()
        self.last_targets: list[Target] = []

    def update(self, result: Result | None, t_s: float) -> list[Track]:
        self.last_targets = [] if result is None else targets_of(result)
        return self.tracker.update(self.last_targets, t_s)

    def best_track(self, tracks: list[Track]) -> Track | None:
        """The track of the acquisition's best target, if it is on one."""
        if not self.last_targets or self.last_targets[0].track_id is None:
            return None
        wanted = self.last_targets[0].track_id
        return next((t for t in tracks if t.track_id == wanted), None)

    def reset(self) -> None:
        self.tracker.reset()


def track_records(tracks: list[Track]) -> list[dict]:
    return [t.record() for t in tracks]


@dataclass
class Timed:
    recording: Recording
    t_s: float
    new_run: bool  # first acquisition of a recording: the tracker restarts here


def time_ordered(recordings: Iterable[Recording]) -> Iterator[Timed]:
    """Recordings in time order with a nominal time each (see the module docstring)."""
    items = list(recordings)
    keyed = [(_run_and_index(r.source), n, r) for n, r in enumerate(items)]
    keyed.sort(key=lambda item: (item[0][0], item[0][1], item[1]))
    previous = None
    for (run, index, _), _, rec in keyed:
        yield Timed(rec, index * NOMINAL_PERIOD_S, run != previous)
        previous = run


def _run_and_index(source: str) -> tuple[str, int, int]:
    for pattern in (_CSV_NAME, _MCAP_NAME):
        m = pattern.match(source)
        if m:
            return m["run"], int(m["index"]), 0
    return source, 0, 0  # unknown names: each its own run, in the order given


def replay_tracked(
    pipeline,
    recordings: Iterable[Recording],
    spec: TrackSpec | None = None,
    tracker: ResultTracker | None = None,
) -> Iterator[Replayed]:
    """:func:`spiel_edge.runtime.replay.replay` in time order, each record with ``tracks``."""
    tracker = tracker or ResultTracker(spec or pipeline.profile.track)
    running = RunningBackground.from_profile(pipeline.profile)  # None unless the profile asks
    for item in time_ordered(recordings):
        if item.new_run:
            tracker.reset()
        rec = item.recording
        stand_in = running is not None and rec.background is None and rec.frames is not None
        if stand_in:
            rec = replace(rec, background=running.background())
        (replayed,) = replay(pipeline, [rec])
        tracks = tracker.update(replayed.result, item.t_s)
        if stand_in:
            running.update(rec.frames, tracks)
        replayed.tracks = track_records(tracks)
        yield replayed
