"""Per-board clocks: a board's time (its acquisition stamps) mapped to the host's.

Fusion and scheduling need every board's acquisitions on one time axis. :class:`BoardClock` is
the small interface they use: ``to_host(board_s) -> host_s`` with an ``uncertainty_s``.

:class:`StampClock` is the estimator used when the board offers no TIME_SYNC exchange (protocol
version 1): it learns ``host = offset + (1 + drift) * board`` from the stamps of the
acquisitions and the host times they arrived. Transport only ever delays, so the line is fitted
to the lower envelope of the (board, arrival - board) points: the minimum of each block of
``BLOCK`` acquisitions, a least-squares line through the last ``BLOCKS`` minima. The mapped
time is therefore the acquisition's time plus the link's *smallest* latency (a constant bias
the estimator cannot see), and a delayed acquisition does not move it. A board whose clock
goes back (a reset) starts the estimate afresh. A board that speaks protocol version 2 gives
each acquisition ``stamp_host`` from its TIME_SYNC estimator (device/timesync.py), which
robot/serve.py uses instead; this estimate serves version-1 boards, acquisitions before the
sync converged, and ``fuse``'s mapping of other computers' clocks.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Protocol

import numpy as np

BLOCK = 8  # acquisitions per lower-envelope point
BLOCKS = 64  # lower-envelope points in the fit
MIN_DRIFT_SPAN_S = 10.0  # the drift is fitted once the minima span this long (else 0)
MAX_DRIFT = 1e-3  # a crystal drifts by ppm, never by 0.1 %
MAX_DISAGREEMENT_S = 1.0  # a mapped time this far from arrival: the clock is not believable
MAX_BACKLOG_S = 10.0  # a record older than this on arrival is refused, not waited for (fuse)
DISAGREE_LIMIT = 3  # times in a row from the future: the clocks disagree
BEHIND_FOR_S = 5.0  # times this long all seconds in the past: the clocks disagree


class BoardClock(Protocol):
    def to_host(self, board_s: float) -> float: ...

    @property
    def uncertainty_s(self) -> float: ...


class StampClock:
    """See the module docstring. ``observe`` every acquisition, then ``to_host``."""

    def __init__(self) -> None:
        self.resets = 0
        self._reset()

    def _reset(self) -> None:
        self._block: list[tuple[float, float]] = []
        self._minima: deque[tuple[float, float]] = deque(maxlen=BLOCKS)
        self._offset = None  # host = offset + (1 + drift) * board
        self._drift = 0.0
        self._last_board = None
        self._spread = float("inf")
        self._first_min: tuple[float, float] | None = None

    @property
    def ready(self) -> bool:
        return self._offset is not None

    @property
    def drift(self) -> float:
        """Host seconds per board second, minus 1 (a board clock that runs fast: negative).
        A board period of ``P / (1 + drift)`` board seconds lasts ``P`` host seconds."""
        return self._drift

    @property
    def uncertainty_s(self) -> float:
        return self._spread

    def observe(self, board_s: float, arrival_s: float) -> float:
        """Take one acquisition's stamp and arrival; returns how late it arrived against the
        estimate before it (seconds; seconds off: the clocks disagree)."""
        if self._last_board is not None and board_s < self._last_board:
            self.resets += 1
            self._reset()
        self._last_board = board_s
        delay = arrival_s - board_s
        if not self._minima:
            self._offset = delay if self._offset is None else min(self._offset, delay)
        late = delay - (self._offset + self._drift * board_s)
        self._block.append((board_s, delay))
        if len(self._block) >= BLOCK:
            self._minima.append(min(self._block, key=lambda p: p[1]))
            self._block = []
            self._fit()
        return late

    def _fit(self) -> None:
        pts = np.array(self._minima)
        x, y = pts[:, 0], pts[:, 1]
        slope = 0.0
        if x[-1] - x[0] >= MIN_DRIFT_SPAN_S:
            xm = x.mean()
            sxx = float(((x - xm) ** 2).sum())
            slope = float(((x - xm) * (y - y.mean())).sum() / sxx) if sxx > 0 else 0.0
            slope = max(-MAX_DRIFT, min(MAX_DRIFT, slope))
        resid = y - slope * x
        if slope == 0.0:  # no drift known yet: only the recent points set the level
            resid = resid[-4:]
        # the line through the lower envelope: transport only delays, so its lowest point
        self._offset = float(resid.min())
        self._drift = slope
        self._spread = float(np.max(np.abs(resid - self._offset)))

    def to_host(self, board_s: float) -> float:
        if self._offset is None:
            raise ValueError("no acquisition observed yet")
        return board_s + self._offset + self._drift * board_s


class Disagreement:
    """Whether two clocks disagree, from how late each time arrives against the other clock
    (``late_s``: arrival minus the time; delivery only ever delays). A time from the future by
    more than ``MAX_DISAGREEMENT_S``, ``DISAGREE_LIMIT`` in a row, is an offset no delay explains.
    A time from the past may be a host or a network behind (on a loaded machine a reader ran
    1.3-1.7 s behind for a while and a board was dropped for it): only when every time for
    ``BEHIND_FOR_S`` of arrivals is that late do the clocks disagree."""

    def __init__(self) -> None:
        self._ahead = 0
        self._behind_since: float | None = None

    def observe(self, late_s: float, arrival_s: float) -> bool:
        if late_s < -MAX_DISAGREEMENT_S:
            self._ahead += 1
            self._behind_since = None
            return self._ahead >= DISAGREE_LIMIT
        self._ahead = 0
        if late_s <= MAX_DISAGREEMENT_S:
            self._behind_since = None
            return False
        if self._behind_since is None:
            self._behind_since = arrival_s
        return arrival_s - self._behind_since >= BEHIND_FOR_S


def synced_pulse(acq) -> float | None:
    """The acquisition's pulse on this process's ``perf_counter`` axis from protocol version
    2's ``stamp_host`` (the board's time of its first sample mapped by TIME_SYNC, Unix
    seconds), or None from a version-1 board or before the clocks are synced."""
    stamp = getattr(acq, "stamp_host", None)
    if stamp is None:
        return None
    return stamp - unix_minus_perf_s()


def unix_minus_perf_s() -> float:
    """``time.time() - time.perf_counter()`` from reads taken together: of three pairs, the one
    whose two ``perf_counter`` reads around ``time.time()`` lie closest. (An acquisition's
    ``host_time`` and ``received_ns`` are not such a pair: the acquisition is assembled after
    its bytes were read, milliseconds later on a loaded computer, which moved its pulse.)"""
    best, offset = float("inf"), 0.0
    for _ in range(3):
        before = time.perf_counter_ns()
        wall = time.time_ns()
        after = time.perf_counter_ns()
        if after - before < best:
            best, offset = after - before, (wall - (before + after) / 2) / 1e9
    return offset


def wait_until(at: float, stop: threading.Event) -> bool:
    """Sleep until perf_counter() reaches ``at`` (spinning the last 2 ms); False if stopped."""
    while not stop.is_set():
        wait = at - time.perf_counter()
        if wait <= 0:
            return True
        time.sleep(wait - 0.002 if wait > 0.003 else 0)
    return False
