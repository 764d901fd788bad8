"""Multi-target tracker: ``Tracker(spec).update(targets, t_s) -> list[Track]``.

Per acquisition: every track is predicted to ``t_s`` (an IMM of a near-static and a
constant-velocity model, imm.py; the latter alone with the IMM off), targets are gated
on the squared Mahalanobis distance with the predicted and the target's covariance, matched
by one global assignment (confirmed tracks first), and the matched tracks updated. A track is
born tentative from a target no track took and confirmed after ``confirm_hits`` hits within
``confirm_window`` acquisitions (it then gets the next integer id, never reused); a confirmed
track is deleted after ``max_misses`` misses in a row. At most ``max_tracks`` tracks exist at
once (births beyond are dropped and counted) and at most ``MAX_TARGETS`` targets per update are
used (the best first). Time going backwards or a gap over ``max_gap_s`` restarts the tracker
(every track dropped; ids go on counting). Outputs are always finite and the covariances
symmetric.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from itertools import repeat
from typing import Protocol

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.track.layout import (
    CONFIRMED,
    DROPPED,
    HITS,
    ID,
    MISSES,
    NEXT_ID,
    SLOTS,
    STATUS,
    allocate,
    measurement_views,
    snapshot_meta,
    snapshot_rows,
    state_views,
    target_ids,
)
from spiel_edge.track.step import snapshot_now, step_buffered

log = logging.getLogger(__name__)

MAX_TARGETS = SLOTS  # targets used per update (the first, i.e. best, ones)


class TargetLike(Protocol):
    position_mm: np.ndarray
    covariance_mm2: np.ndarray
    track_id: int | None


class Track:
    """A confirmed track's state after an update (a snapshot, not updated later)."""

    __slots__ = ("_meta", "_row", "_snapshot")

    def __init__(self, meta: list[int], snapshot: np.ndarray, row: int):
        self._meta = meta  # per row of the snapshot: id, age, hits, misses (flat)
        self._snapshot, self._row = snapshot, row  # row: state (6), covariance (36)

    @property
    def track_id(self) -> int:
        return self._meta[4 * self._row]

    @property
    def age(self) -> int:
        """Acquisitions since birth."""
        return self._meta[4 * self._row + 1]

    @property
    def hits(self) -> int:
        """Acquisitions with a target."""
        return self._meta[4 * self._row + 2]

    @property
    def misses(self) -> int:
        """Acquisitions without one, in a row."""
        return self._meta[4 * self._row + 3]

    @property
    def state(self) -> np.ndarray:
        """(6,): position mm, velocity mm/s."""
        return self._snapshot[self._row, :6]

    @property
    def state_covariance(self) -> np.ndarray:
        """(6, 6), symmetric."""
        return self._snapshot[self._row, 6:].reshape(6, 6)

    @property
    def position_mm(self) -> np.ndarray:
        return self._snapshot[self._row, :3]

    @property
    def velocity_mm_s(self) -> np.ndarray:
        return self._snapshot[self._row, 3:6]

    @property
    def covariance_mm2(self) -> np.ndarray:
        return self._snapshot[self._row, 6:].reshape(6, 6)[:3, :3]

    def record(self) -> dict:
        row = self._snapshot[self._row].tolist()  # one conversion: state, then 6 x 6 covariance
        return {
            "track_id": int(self.track_id),
            "position_mm": _three(row, 0, 2),
            "velocity_mm_s": _three(row, 3, 2),
            "covariance_mm2": [_three(row, 6, 3), _three(row, 12, 3), _three(row, 18, 3)],
            # the velocity block of the 6 x 6 covariance: rows and columns 3-5
            "velocity_covariance_mm2_s2": [
                _three(row, 27, 3),
                _three(row, 33, 3),
                _three(row, 39, 3),
            ],
            "age": int(self.age),
            "hits": int(self.hits),
        }

    def __repr__(self) -> str:
        pos = ", ".join(f"{v:.1f}" for v in self.position_mm)
        return f"Track({self.track_id}, [{pos}] mm, age {self.age}, hits {self.hits})"


def _three(row: list[float], at: int, digits: int) -> list[float]:
    """row[at : at + 3] rounded (a record's vector or covariance row; no comprehension: this
    runs for every track of every record)."""
    return [round(row[at], digits), round(row[at + 1], digits), round(row[at + 2], digits)]


class Tracker:
    """Tracks targets across acquisitions; see the module docstring and docs/tracking.md."""

    def __init__(self, spec: TrackSpec | None = None):
        self.spec = spec = spec or TrackSpec()
        params = np.array(
            [
                spec.acceleration_mm_s2,
                spec.gate_chi2,
                spec.measurement_floor_mm**2,
                spec.fallback_sigma_mm**2,
                spec.initial_speed_mm_s**2,
                spec.confirm_hits,
                spec.confirm_window,
                spec.max_misses,
                spec.imm_static_noise_mm**2,
                spec.imm_switch_probability,
                spec.imm_static_share,
            ],
            dtype=np.float64,
        )
        self._arrays = allocate(spec.max_tracks, params)
        self._x, self._p, self._meta, self._counts = state_views(*self._arrays[:2])
        self._z, self._r = measurement_views(self._arrays[0])
        self._last_t: float | None = None
        self.restarts = 0

    @property
    def dropped_births(self) -> int:
        """Targets that would have started a track while ``max_tracks`` were in use."""
        return int(self._counts[DROPPED])

    @property
    def ids_issued(self) -> int:
        """Track ids handed out so far (the next new track gets this id)."""
        return int(self._counts[NEXT_ID])

    def reset(self) -> None:
        """Forget every track (ids keep counting, so an id never names two objects)."""
        self._meta[STATUS] = 0
        self._meta[ID] = -1
        self._last_t = None

    def update(self, targets: Sequence[TargetLike], t_s: float) -> list[Track]:
        """Tracks after the acquisition at ``t_s`` seconds; sets ``track_id`` on the targets
        matched to confirmed tracks (None on the others). Confirmed tracks, by id."""
        t = float(t_s)
        if not math.isfinite(t):
            raise InputError(f"tracker: acquisition time must be finite, got {t_s!r}")
        dt = self._advance(t)
        used, m = targets, len(targets)
        if m > MAX_TARGETS:  # the step's buffers hold SLOTS (= MAX_TARGETS) targets
            used, m = targets[:MAX_TARGETS], MAX_TARGETS
        self._write_measurements(used)
        floats, ints, bools = self._arrays
        snapshot = snapshot_rows(floats, step_buffered(floats, ints, bools, m, dt))
        for target, track_id in zip(used, target_ids(ints, m), strict=True):
            target.track_id = None if track_id < 0 else track_id
        if used is not targets:
            for target in targets[MAX_TARGETS:]:
                target.track_id = None
        return _tracks(snapshot, ints)

    def confirmed_state(self) -> tuple[np.ndarray, ...]:
        """The confirmed tracks as they stand (before the next update's prediction): slots,
        ids, hits, states (n, 6) and covariances (n, 6, 6), copies; for a caller deciding which
        tracks the next update may not charge a miss (:meth:`hold_misses`)."""
        slots = np.flatnonzero(self._meta[STATUS] == CONFIRMED)
        return (
            slots,
            self._meta[ID, slots].copy(),
            self._meta[HITS, slots].copy(),
            self._x[slots].copy(),
            self._p[slots].copy(),
        )

    @property
    def last_time(self) -> float | None:
        """The time of the last update (None before the first, or after a restart)."""
        return self._last_t

    def hold_misses(self, slots: np.ndarray) -> None:
        """The next update charges these tracks (slots from :meth:`confirmed_state`) no miss:
        they could not have been seen (e.g. outside every sensor's field of view). A hit
        still counts; the step adds one miss, which this takes back beforehand."""
        self._meta[MISSES, slots] -= 1

    def _write_measurements(self, targets: Sequence[TargetLike]) -> None:
        """:func:`measurements` into the step's buffers: the same numbers (a target's
        arrays are assigned as they are; anything else takes the general path)."""
        z, r = self._z, self._r
        try:
            for j, target in enumerate(targets):
                z[j] = target.position_mm
                r[j] = target.covariance_mm2
        except (TypeError, ValueError):
            m = len(targets)
            z[:m], r[:m] = measurements(targets)

    def tracks(self) -> list[Track]:
        """The confirmed tracks now, by id."""
        floats, ints, bools = self._arrays
        return _tracks(snapshot_rows(floats, snapshot_now(floats, ints, bools)), ints)

    def _advance(self, t: float) -> float:
        last, self._last_t = self._last_t, t
        if last is None:
            return 0.0
        dt = t - last
        if dt < 0 or dt > self.spec.max_gap_s:
            if self._meta[STATUS].any():
                log.info("tracker restarts: %s (%.3f s)", "time went back" if dt < 0 else "gap", dt)
            self.restarts += 1
            self.reset()
            self._last_t = t
            return 0.0
        return dt


def _tracks(snapshot: np.ndarray, ints: np.ndarray) -> list[Track]:
    """Track objects on one snapshot (a row per track: state, covariance)."""
    n = len(snapshot)
    return list(map(Track, repeat(snapshot_meta(ints, n), n), repeat(snapshot, n), range(n)))


def measurements(targets: Sequence[TargetLike]) -> tuple[np.ndarray, np.ndarray]:
    """Positions (m, 3) and covariances (m, 3, 3); a malformed one becomes NaN (the step
    then skips the position, or uses the fallback covariance)."""
    m = len(targets)
    try:  # the usual case in one go
        z = np.array([t.position_mm for t in targets], dtype=np.float64).reshape(m, 3)
        r = np.array([t.covariance_mm2 for t in targets], dtype=np.float64).reshape(m, 3, 3)
        return z, r
    except (TypeError, ValueError):
        pass
    z = np.empty((m, 3))
    r = np.empty((m, 3, 3))
    for j, target in enumerate(targets):
        try:
            z[j] = target.position_mm
        except (TypeError, ValueError):
            z[j] = np.nan
        try:
            r[j] = target.covariance_mm2
        except (TypeError, ValueError):
            r[j] = np.nan
    return z, r
