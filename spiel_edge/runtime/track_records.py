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
from spiel_edge.runtime.recorded import Replayed, replay
from spiel_edge.runtime.static_scene import RunningBackground
from spiel_edge.track import Track, Tracker

NOMINAL_PERIOD_S = 0.02  # between recorded acquisitions (50 Hz, `run --rate`'s default)
# The covariance calibration ([scene] s, f) the tracker's settings were chosen with. The
# published covariance is calibrated for 95 % coverage on unseen positions (issue 26:
# without a background its ellipsoids take in the wrong associations' tail, eight times
# wider), which as measurement noise makes the filter sluggish; the tracker is fed each
# target's covariance re-expressed in this calibration instead (C = s^2 L + f^2 I is exact).
TRACKER_COVARIANCE_SCALE = 0.95
TRACKER_COVARIANCE_FLOOR_MM = 8.0
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


def tracker_covariance(covariance_mm2: np.ndarray, scale: float, floor_mm: float) -> np.ndarray:
    """A target's covariance ``s^2 L + f^2 I`` (the profile's calibration ``scale``,
    ``floor_mm``) re-expressed as the tracker's: TRACKER_COVARIANCE_SCALE^2 L +
    TRACKER_COVARIANCE_FLOOR_MM^2 I. A covariance that cannot be the pipeline's (not finite,
    or a variance below the floor) is passed on as it is. One 3 x 3 or a stack (K, 3, 3),
    each judged on its own (one call per acquisition, not per target)."""
    cov = np.asarray(covariance_mm2, dtype=np.float64)
    floor2 = floor_mm**2
    usable = np.isfinite(cov).all(axis=(-2, -1)) & (
        np.diagonal(cov, axis1=-2, axis2=-1) >= floor2
    ).all(axis=-1)
    eye = np.eye(3)
    linear = (cov - floor2 * eye) / scale**2
    mapped = TRACKER_COVARIANCE_SCALE**2 * linear + TRACKER_COVARIANCE_FLOOR_MM**2 * eye
    return np.where(usable[..., None, None], mapped, cov)


class ResultTracker:
    """A Tracker fed with pipeline results; keeps each result's targets' ``track_id``.

    With ``scene`` (the profile's [scene]) each target reaches the tracker with its covariance
    in the calibration the tracker was tuned with (:func:`tracker_covariance`); ``update``'s
    ``captured`` says whether the acquisition had a captured background (which scale made
    it). The targets in the records keep the published covariance."""

    def __init__(self, spec: TrackSpec, scene=None):
        self.tracker = Tracker(spec)
        self.tracker.update([], 0.0)  # compile (or load) the kernels before the stream starts
        self.tracker.reset()
        self.scene = scene
        self.last_targets: list[Target] = []

    def update(
        self, result: Result | None, t_s: float, captured: bool | None = True
    ) -> list[Track]:
        """``captured`` None: the targets are not the pipeline's (an oracle): fed as they are."""
        self.last_targets = [] if result is None else targets_of(result)
        if self.scene is None or captured is None or not self.last_targets:
            return self.tracker.update(self.last_targets, t_s)
        sc = self.scene
        scale = sc.covariance_scale if captured else sc.covariance_scale_no_background
        covariances = tracker_covariance(
            np.array([t.covariance_mm2 for t in self.last_targets]), scale, sc.covariance_floor_mm
        )
        fed = [
            replace(t, covariance_mm2=cov)
            for t, cov in zip(self.last_targets, covariances, strict=True)
        ]
        tracks = self.tracker.update(fed, t_s)
        for target, copy in zip(self.last_targets, fed, strict=True):
            target.track_id = copy.track_id
        return tracks

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
    keyed = [(run_and_index(r.source), n, r) for n, r in enumerate(items)]
    keyed.sort(key=lambda item: (item[0][0], item[0][1], item[1]))
    previous = None
    for (run, index, _), _, rec in keyed:
        yield Timed(rec, index * NOMINAL_PERIOD_S, run != previous)
        previous = run


def run_and_index(source: str) -> tuple[str, int, int]:
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
    """:func:`spiel_edge.runtime.recorded.replay` in time order, each record with ``tracks``."""
    profile = pipeline.profile
    tracker = tracker or ResultTracker(spec or profile.track, profile.scene)
    running = RunningBackground.from_profile(pipeline.profile)  # None unless the profile asks
    for item in time_ordered(recordings):
        if item.new_run:
            tracker.reset()
        rec = item.recording
        stand_in = running is not None and rec.background is None and rec.frames is not None
        if stand_in:
            rec = replace(rec, background=running.background())
        (replayed,) = replay(pipeline, [rec])
        captured = rec.background is not None and profile.preprocess.background_subtraction
        tracks = tracker.update(replayed.result, item.t_s, captured)
        if stand_in:
            running.update(rec.frames, tracks)
        replayed.tracks = track_records(tracks)
        yield replayed
