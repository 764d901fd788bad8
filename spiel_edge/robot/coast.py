"""Field-of-view-aware track maintenance for the fused tracker (robot/fusion.py).

A board can only miss what it could have seen. Before each cycle's update every confirmed
track is predicted to the cycle's time (constant velocity); a track whose predicted position
lies outside every board's detection cone (``detection_deg`` off the board's facing, or
beyond ``range_mm``) is charged no miss that cycle: it coasts on its motion model (the
tracker's prediction, its covariance growing with the process noise) and is re-associated
through its grown Mahalanobis gate when a board sees it again, keeping its id. The coast is
bounded: ``max_coast_s`` since the track's last hit, and a position standard deviation of
``max_sigma_mm`` (the largest of its three, at the last update); beyond either, misses count
again and the track is deleted after the tracker's ``max_misses`` as usual.

Pure logic: the cones are the robot file's mounts, the state the tracker's
(``Tracker.confirmed_state`` / ``hold_misses``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

MAX_COAST_S = 1.5  # longest coast outside every field of view since the last hit
MAX_SIGMA_MM = 500.0  # a track this uncertain (std, any axis) is charged misses again


class CoastPolicy:
    """Which confirmed tracks the next update may not charge a miss (see the module
    docstring). ``cones``: per board (origin mm (3,), facing (3,), half-angle deg), in the
    frame tracks are predicted in after ``to_base`` (base_link)."""

    def __init__(
        self,
        cones: list[tuple[np.ndarray, np.ndarray, float]],
        *,
        range_mm: float,
        max_coast_s: float = MAX_COAST_S,
        max_sigma_mm: float = MAX_SIGMA_MM,
    ):
        self._origin = np.array([c[0] for c in cones], float).reshape(-1, 3)
        facing = np.array([c[1] for c in cones], float).reshape(-1, 3)
        self._facing = facing / np.linalg.norm(facing, axis=1, keepdims=True)
        self._cos = np.cos(np.radians([c[2] for c in cones]))
        self.range_mm = float(range_mm)
        self.max_coast_s = float(max_coast_s)
        self.max_var = float(max_sigma_mm) ** 2
        self._last_hit: dict[int, tuple[int, float]] = {}  # track id: (hits, time of last hit)
        self.held = 0  # track-cycles held so far (diagnostics)

    @classmethod
    def from_robot(cls, robot, **kw) -> CoastPolicy:
        """Every board's cone: its mount's origin and facing, its ``detection_deg``; the
        range the trigger's ``max_range_m``."""
        cones = [(b.mount.translation_mm, b.mount.facing, b.detection_deg) for b in robot.boards]
        return cls(cones, range_mm=robot.trigger.max_range_m * 1000.0, **kw)

    def visible(self, pos_mm: np.ndarray) -> np.ndarray:
        """(n,) True where a position (n, 3) is inside some board's detection cone."""
        v = np.asarray(pos_mm, float)[:, None, :] - self._origin[None, :, :]
        d = np.linalg.norm(v, axis=2)
        cos = np.einsum("nbk,bk->nb", v, self._facing) / np.maximum(d, 1e-9)
        return np.any((cos >= self._cos) & (d <= self.range_mm), axis=1)

    def hold(
        self,
        tracker,
        t: float,
        to_base: Callable[[np.ndarray], np.ndarray | None] | None = None,
    ) -> np.ndarray:
        """Before ``tracker.update(..., t)``: holds the miss count of the confirmed tracks
        predicted outside every cone (within the coast's bounds); their ids. ``to_base`` maps
        predicted positions into the cones' frame (None from it: no track is held)."""
        slots, ids, hits, x, p = tracker.confirmed_state()
        last = tracker.last_time
        previous, self._last_hit = self._last_hit, {}
        if last is None or not len(slots):
            return ids[:0]
        for i, h in zip(ids.tolist(), hits.tolist(), strict=True):
            seen = previous.get(i)  # a change in hits: the last update was a hit
            self._last_hit[i] = seen if seen is not None and seen[0] == h else (h, last)
        dt = t - last
        if not (math.isfinite(dt) and dt >= 0.0):
            return ids[:0]
        pos = x[:, :3] + x[:, 3:] * dt
        if to_base is not None:
            pos = to_base(pos)
            if pos is None:
                return ids[:0]
        coast_s = t - np.array([self._last_hit[i][1] for i in ids.tolist()])
        var = np.max(np.diagonal(p[:, :3, :3], axis1=1, axis2=2), axis=1)
        held = ~self.visible(pos) & (coast_s <= self.max_coast_s) & (var <= self.max_var)
        tracker.hold_misses(slots[held])
        self.held += int(held.sum())
        return ids[held]
