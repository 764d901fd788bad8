"""Fusion in the robot's frame: every board's targets in ``base_link``, one tracker over all.

Data flow: per board, the pipeline's targets (board frame, mm, 3 x 3 covariance) ->
:func:`to_base` (``p = R p_b + t``, ``C = R C_b R^T``) -> :class:`Fuser`, which gathers the
boards' acquisitions of one trigger cycle (the schedule's period, on the host's time axis:
each board's stamps mapped through its clock, robot/clock.py), merges the targets two boards
saw of one object (within the Mahalanobis gate of each other: one information-weighted
target), and updates one multi-target tracker (spiel_edge/track) at the cycle's mean time.
Updating once per cycle keeps a track outside one board's field of view from counting that
board's acquisition as a miss; a target passing from one field of view into the next keeps
its track (as far as the boards see it: docs/robot.md). Each target is first moved to the
cycle's time with the velocity of the confirmed track it is near. The fused record goes out
when every board expected has reported for the cycle, or ``WAIT_CYCLES`` cycles later.

Optionally in ``odom``: given the robot's pose in ``odom`` at a time (``odometry``, a
callable), each board's targets go on into ``odom`` at their acquisition's time before
tracking, so the robot's own motion is not the targets' motion; an acquisition with no pose
at its time (none yet, or the stream stalled) is left out (``stats[board]["no_pose"]``). With
a ``coast`` policy (robot/coast.py) a track predicted outside every board's view is charged no
miss for the cycle: it coasts across the gaps between fields of view.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.description import Mount
from spiel_edge.robot.odometry import OdometryBuffer, planar_pose
from spiel_edge.track import Tracker

log = logging.getLogger(__name__)
__all__ = [
    "BaseTarget",
    "BoardReport",
    "Fuser",
    "OdometryBuffer",
    "merge_targets",
    "planar_pose",
    "stamp_latency",
]

WAIT_CYCLES = 3  # an incomplete cycle is fused once a report this many cycles later arrives
QUIET_CYCLES = 3  # a board missing this many cycles in a row is not waited for
ALIGN_MM = 60.0  # a target this near a confirmed track moves with it to the cycle's time
MERGE_CHI2 = 11.34  # two boards' targets closer than this (3 dof, 99 %) are one object


@dataclass
class BaseTarget:
    """One target in the fusion frame (``track_id`` set by the tracker)."""

    position_mm: np.ndarray
    covariance_mm2: np.ndarray
    boards: list[str]
    score: float = 0.0
    track_id: int | None = None

    def record(self) -> dict:
        out = {
            "position_mm": np.round(self.position_mm, 2).tolist(),
            "covariance_mm2": np.round(self.covariance_mm2, 3).tolist(),
            "boards": self.boards,
            "score": round(float(self.score), 4),
        }
        if self.track_id is not None:
            out["track_id"] = int(self.track_id)
        return out


def to_base(mount: Mount, position_mm, covariance_mm2) -> tuple[np.ndarray, np.ndarray]:
    """A board-frame target into base_link (covariance rotated; symmetric)."""
    p = mount.to_base(np.asarray(position_mm, float))
    c = mount.covariance_to_base(np.asarray(covariance_mm2, float))
    return p, 0.5 * (c + c.T)


def merge_targets(
    targets: list[BaseTarget], chi2: float = MERGE_CHI2, near_mm: float | None = None
) -> list[BaseTarget]:
    """Targets of different boards that are one object (Mahalanobis distance of their
    difference under the sum of their covariances below ``chi2``) fused, nearest pairs
    first, into one information-weighted target. Targets of one board are never merged
    (the board's own scene stage already kept them apart)."""
    out = list(targets)
    while len(out) > 1:
        n = len(out)
        i, j = np.triu_indices(n, 1)
        boards = [set(t.boards) for t in out]
        ok = np.array([not (boards[a] & boards[b]) for a, b in zip(i, j, strict=True)])
        if not ok.any():
            break
        i, j = i[ok], j[ok]
        pos = np.array([t.position_mm for t in out])
        cov = np.array([t.covariance_mm2 for t in out])
        d = pos[i] - pos[j]
        try:
            d2 = np.einsum("ki,ki->k", d, np.linalg.solve(cov[i] + cov[j], d[:, :, None])[:, :, 0])
        except np.linalg.LinAlgError:
            d2 = np.full(len(i), np.inf)
        if near_mm is not None:  # this near: one object whatever the covariances
            d2 = np.where(np.einsum("ki,ki->k", d, d) < near_mm * near_mm, 0.0, d2)
        k = int(np.argmin(d2))
        if not d2[k] < chi2:
            break
        a, b = out[int(i[k])], out[int(j[k])]
        try:
            ia, ib = np.linalg.inv(a.covariance_mm2), np.linalg.inv(b.covariance_mm2)
            c = np.linalg.inv(ia + ib)
        except np.linalg.LinAlgError:
            break
        c = 0.5 * (c + c.T)
        p = c @ (ia @ a.position_mm + ib @ b.position_mm)
        merged = BaseTarget(p, c, a.boards + b.boards, max(a.score, b.score))
        out = [t for m, t in enumerate(out) if m not in (int(i[k]), int(j[k]))] + [merged]
    return out


@dataclass
class BoardReport:
    """One board's acquisition, as the fuser takes it."""

    board: str
    host_time: float  # the acquisition on the host's time axis (its clock mapped)
    targets: list[tuple[np.ndarray, np.ndarray, float]]  # board frame: position, covariance, score
    acquisition: int = -1
    device_time_us: int | None = None
    crosstalk: list[str] = field(default_factory=list)  # boards whose pulse reached its window
    error: str | None = None
    truth_mm: np.ndarray | None = None  # (K, 3) in base_link, when the source knows it
    acquired_unix: float | None = None  # when the acquisition reached its host (Unix time)
    received_unix: float | None = None  # when its record reached the fuser (``fuse``: Unix time)
    time_uncertainty_s: float | None = None  # of host_time, when measured (TIME_SYNC)


class Fuser:
    """See the module docstring. ``add(report)`` returns the fused records it completes."""

    def __init__(
        self,
        mounts: dict[str, Mount],
        *,
        period_s: float,
        spec: TrackSpec | None = None,
        frame_id: str = "base_link",
        odometry: Callable[[float], tuple[np.ndarray, np.ndarray] | None] | None = None,
        drop_marked: bool = True,
        track: bool = True,
        field_of_view_deg: dict[str, float] | None = None,
        coast: CoastPolicy | None = None,
        unix_offset: Callable[[], float] | None = None,
    ):
        self.mounts = dict(mounts)
        # the reports' time axis to Unix time in the records (run --robot times pulses on
        # perf_counter; `run` and `fuse` records are Unix already): one clock in every record
        self.unix_offset = unix_offset
        fov = field_of_view_deg or {}
        # a target further off its board's facing than this is not fused (cosine, board frame)
        self._fov_cos = {n: math.cos(math.radians(fov.get(n, 90.0))) for n in mounts}
        self.period_s = period_s
        self.frame_id = frame_id
        self.odometry = odometry
        self.drop_marked = drop_marked  # targets of an acquisition marked with cross-talk
        self.tracker = Tracker(spec) if track else None
        self.coast = coast  # tracks outside every board's view are charged no miss (coast.py)
        if self.tracker is not None:  # compile (or load) its kernels now, not at the first cycle
            self.tracker.update([], 0.0)
            self.tracker.reset()
        self.expected = set(mounts)  # boards a cycle waits for (dropped boards leave it)
        self._gone: set[str] = set()  # dropped for good
        self._misses = dict.fromkeys(mounts, 0)  # cycles fused without the board, in a row
        self._t_ref: float | None = None
        self._phase: dict[str, float] = {}  # each board's pulse within the cycle (s)
        self._open: dict[int, dict[str, BoardReport]] = {}
        self._done = -1  # cycles up to this one are fused
        self._motion = (0.0, np.zeros((0, 3)), np.zeros((0, 3)))  # the last confirmed tracks
        self.seq = 0
        self.stats = {
            name: {"reports": 0, "targets": 0, "marked": 0, "late": 0, "no_pose": 0}
            for name in mounts
        }

    def set_schedule(self, t0: float, offsets: dict[str, float]) -> None:
        """Boards in trigger slots: cycle k holds every board's pulse at ``t0 + k period +
        offset`` (instead of phases learned from the first reports)."""
        self._t_ref = t0
        self._phase.update(offsets)

    def _align(self, p: np.ndarray, t_b: float, t: float) -> np.ndarray:
        """A target seen at ``t_b`` moved to the cycle's time ``t`` with the velocity of the
        confirmed track it is nearest to (within ``ALIGN_MM`` of that track at ``t_b``); the
        boards of one cycle fire up to a period apart."""
        t_last, pos, vel = self._motion
        if not len(pos):
            return p
        d = np.linalg.norm(pos + vel * (t_b - t_last) - p, axis=1)
        k = int(np.argmin(d))
        return p + vel[k] * (t - t_b) if d[k] < ALIGN_MM else p

    def _to_base_at(self, t: float):
        """Positions in the tracking frame into base_link at ``t`` (None: pose unknown)."""
        if self.odometry is None:
            return None
        pose = self.odometry(t)
        return lambda p: None if pose is None else (p - pose[1]) @ pose[0]

    def drop(self, board: str) -> None:
        """A board gone for good: cycles no longer wait for it."""
        self._gone.add(board)
        self.expected.discard(board)

    def restore(self, board: str) -> None:
        """A dropped board reports again: it is waited for once it has reported."""
        self._gone.discard(board)

    def _cycle(self, board: str, t: float) -> int:
        """The cycle of a report: each board keeps its place (phase) within the period,
        learned from its first report and followed slowly (clocks drift), so reports that
        arrive out of order or late still land in their own cycle."""
        p = self.period_s
        if self._t_ref is None:
            self._t_ref = t
        x = t - self._t_ref
        if board not in self._phase:
            self._phase[board] = x % p
        k = round((x - self._phase[board]) / p)
        resid = x - self._phase[board] - k * p
        self._phase[board] += 0.05 * resid
        return k

    def add(self, report: BoardReport) -> list[dict]:
        """Take one board's acquisition; the fused records it completes. A cycle is fused
        when every board expected has reported for it, or once a report ``WAIT_CYCLES`` cycles
        later arrives (a board is missing). A board missing from ``QUIET_CYCLES`` cycles in a row
        is not waited for until it reports again."""
        if report.board not in self.mounts:
            raise KeyError(report.board)
        st = self.stats[report.board]
        st["reports"] += 1
        st["targets"] += len(report.targets)
        st["marked"] += bool(report.crosstalk)
        k = self._cycle(report.board, report.host_time)
        if report.board not in self._gone:  # back (or late): the next cycles wait for it
            self.expected.add(report.board)
            self._misses[report.board] = 0
        if k <= self._done:
            st["late"] += 1  # its cycle is already out
            return []
        self._open.setdefault(k, {})[report.board] = report
        out: list[dict] = []
        for c in sorted(self._open):
            if c <= k - WAIT_CYCLES or self.expected <= set(self._open[c]):
                out += self._fuse_upto(c)
        return out

    def _fuse_upto(self, k: int) -> list[dict]:
        out = []
        for c in sorted(c for c in self._open if c <= k):
            reports = self._open.pop(c)
            for name in self.expected - set(reports):
                self._misses[name] += 1
                if self._misses[name] >= QUIET_CYCLES:
                    self.expected.discard(name)
            out += self._fuse(reports)
            self._done = c
        return out

    def flush(self) -> list[dict]:
        """Fuse every open cycle (the end of a stream)."""
        return self._fuse_upto(max(self._open)) if self._open else []

    def _fuse(self, reports: dict[str, BoardReport]) -> list[dict]:
        t = float(np.mean([r.host_time for r in reports.values()]))
        targets: list[BaseTarget] = []
        truths = []
        frame = self.frame_id if self.odometry is None else "odom"
        for r in reports.values():
            if r.truth_mm is not None and len(r.truth_mm):
                truths.append(np.asarray(r.truth_mm, float))
            if r.crosstalk and self.drop_marked:
                continue
            mount = self.mounts[r.board]
            pose = self.odometry(r.host_time) if self.odometry is not None else None
            if self.odometry is not None and pose is None:
                self.stats[r.board]["no_pose"] += 1  # no pose at its time: not in odom
                continue
            fov_cos = self._fov_cos[r.board]
            for pos, cov, score in r.targets:
                if fov_cos > 0 and pos[2] < fov_cos * float(np.linalg.norm(pos)):
                    continue  # outside the board's field of view: poorly located
                p, c = to_base(mount, pos, cov)
                if pose is not None:  # into odom at the acquisition's own time
                    rot, trans = pose
                    p, c = rot @ p + trans, rot @ c @ rot.T
                if not (np.all(np.isfinite(p)) and np.all(np.isfinite(c))):
                    continue
                targets.append(BaseTarget(self._align(p, r.host_time, t), c, [r.board], score))
        fused = merge_targets(targets)
        tracks = None
        if self.tracker is not None:
            if self.coast is not None:
                self.coast.hold(self.tracker, t, self._to_base_at(t))
            confirmed = self.tracker.update(fused, t)
            tracks = [_track_record(tr) for tr in confirmed]
            self._motion = (
                t,
                np.array([tr.position_mm for tr in confirmed]).reshape(-1, 3),
                np.array([tr.velocity_mm_s for tr in confirmed]).reshape(-1, 3),
            )
        offset = self.unix_offset() if self.unix_offset is not None else 0.0
        record = {
            "seq": self.seq,
            "host_time": round(t + offset, 6),
            "frame_id": frame,
            "targets": [f.record() for f in fused],
            "boards": {name: _board_summary(r, offset) for name, r in sorted(reports.items())},
            "missing": sorted(set(self.mounts) - self._gone - set(reports)),
        }
        if tracks is not None:
            record["tracks"] = tracks
        if truths:
            record["truth_targets_mm"] = np.round(truths[0], 2).tolist()
        self.seq += 1
        return [record]


def _track_record(tr) -> dict:
    """A confirmed track as ``Track.record`` gives it (numpy rounding: the same numbers,
    faster)."""
    return {
        "track_id": int(tr.track_id),
        "position_mm": np.round(tr.position_mm, 2).tolist(),
        "velocity_mm_s": np.round(tr.velocity_mm_s, 2).tolist(),
        "covariance_mm2": np.round(tr.covariance_mm2, 3).tolist(),
        "age": int(tr.age),
        "hits": int(tr.hits),
    }


def stamp_latency(record: dict, now: float, latencies_ms: list[float]) -> None:
    """``latency_ms`` (the write against the last board's acquisition) and ``fuser_ms`` (the
    fuser's share: from the last board record's arrival here)."""
    acquired = [b["acquired"] for b in record["boards"].values() if b.get("acquired") is not None]
    if acquired:
        latency = (now - max(acquired)) * 1e3
        record["latency_ms"] = round(latency, 3)
        latencies_ms.append(latency)
    received = [b["received"] for b in record["boards"].values() if "received" in b]
    if received:
        record["fuser_ms"] = round((now - max(received)) * 1e3, 3)


def _board_summary(r: BoardReport, offset: float = 0.0) -> dict:
    out = {
        "acquisition": r.acquisition,
        "host_time": round(r.host_time + offset, 6),
        "targets": len(r.targets),
        "crosstalk": r.crosstalk,
    }
    if r.device_time_us is not None:
        out["device_time_us"] = r.device_time_us
    if r.acquired_unix is not None:
        out["acquired"] = round(r.acquired_unix, 6)
    if r.received_unix is not None:
        out["received"] = round(r.received_unix, 6)
    if r.error:
        out["error"] = r.error
    return out


def reports_targets(result) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """A pipeline result's targets as (position, covariance, score) in the board frame."""
    if result is None:
        return []
    from spiel_edge.runtime.track_records import targets_of

    out = []
    for t in targets_of(result):
        cov = np.asarray(t.covariance_mm2, float)
        if not np.all(np.isfinite(cov)):
            cov = np.eye(3) * 20.0**2
        out.append((np.asarray(t.position_mm, float), cov, float(t.score)))
    return out


def record_targets(record: dict) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """A board record's targets (``run``'s JSON, e.g. from Zenoh) as (position, covariance,
    score); malformed entries are skipped."""
    out = []
    for t in record.get("targets") or []:
        try:
            p = np.asarray(t["position_mm"], float).reshape(3)
            c = np.asarray(t.get("covariance_mm2") or np.eye(3) * 400.0, float).reshape(3, 3)
            s = float(t.get("score", 0.0))
        except (TypeError, ValueError, KeyError, AttributeError):
            continue
        if np.all(np.isfinite(p)) and np.all(np.isfinite(c)):
            out.append((p, c, s))
    return out


def fuse_sequence(fuser: Fuser, reports: Sequence[BoardReport]) -> list[dict]:
    """Every report in order, then the last cycle: the fused records."""
    return [rec for r in reports for rec in fuser.add(r)] + fuser.flush()
