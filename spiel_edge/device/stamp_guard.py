"""Each acquisition's host time stamp, checked against the facts the host has for it.

Pure (no I/O, no clock of its own). The TIME_SYNC estimator (:mod:`.timesync`) maps the board's
time of an acquisition's first sample to the host's clock with an uncertainty; that holds
while the board's clock is the clock its answers describe. Three facts about the acquisition
itself can contradict it:

- the acquisition arrived: its first sample was taken before its last byte was read, so a
  stamp after the arrival (beyond its uncertainty) is impossible -- a clock stepped forward,
  an answer from a clock ahead of the one that stamps the samples;
- acquisitions advance: a board time that stands still or goes back while they do means a
  stuck, wrapped, backwards or restarted clock;
- the host reads frames soon after they are sent. When every stamp of the last
  ``LAG_SPAN_US`` of arrivals lies more than ``MAX_LAG_US`` before its arrival, the mapping is
  off by that much (answers from a clock behind the stamps' one). A shorter such stretch may
  be the host itself, behind on a loaded machine (three boards at 40 Hz beside busy processes
  on two cores ran a 1.3 s backlog): there the stamp states what is known either way -- the
  first sample lies after the mapped value's lower bound and before its arrival -- as the
  middle of that interval with half its width as the uncertainty (``source`` stays "board").

Then, and while the estimator itself does not trust the board's answers, the stamp falls back
to the arrival: the first sample lies in [arrival - span - ``LINK_US``, arrival] (span: the
acquisition's own duration; ``LINK_US``: the transfer and the host's read), the stamp is that
interval's middle and its uncertainty half its width, and ``source`` says ``"arrival"``. A
contradiction from the acquisitions holds until the estimator has kept a new answer.

Stamps never go backwards while acquisitions advance, and never lie after their arrival: a
value below the previous stamp (a refit, a switch between sources) is raised to it, one after
the arrival lowered to it, and the uncertainty widened by the move, so the stated interval
still holds the interval it replaced.
"""

from __future__ import annotations

from dataclasses import dataclass

from spiel_edge.device.timesync import TimeSyncEstimator

__all__ = ["GuardedStamp", "StampGuard"]

LINK_US = 50_000.0  # the last byte read within this of the acquisition's end (USB + host)
MAX_LAG_US = 500_000.0  # a stamp this far before its arrival: the host behind, or the mapping off
LAG_SPAN_US = 30e6  # every stamp of this long this far before its arrival: the mapping is off


@dataclass(frozen=True, slots=True)
class GuardedStamp:
    host_us: float  # the host clock's time of the first sample
    uncertainty_us: float  # about 95 % (the estimator's) or the hard arrival bound
    source: str  # "board": TIME_SYNC's mapping; "arrival": the host's arrival time


class StampGuard:
    def __init__(self, estimator: TimeSyncEstimator) -> None:
        self.estimator = estimator
        self.fallbacks = 0  # stamps from the arrival time
        self.reason: str | None = None  # why the last fallback (for the caller to say once)
        self._prev_board: float | None = None
        self._prev_stamp: float | None = None
        self._doubt_until_used: int | None = None  # the estimator's `used` when doubt began
        self._lagging_since: float | None = None  # arrival of the first of a stretch of lags
        self._boot_id: int | None = None

    def stamp(self, board_us: float, arrival_us: float, span_us: float) -> GuardedStamp | None:
        """The stamp of an acquisition whose first sample the board took at ``board_us``, whose
        last byte the host read at ``arrival_us`` (the estimator's clock), ``span_us`` long;
        None before the first TIME_SYNC answer."""
        est = self.estimator
        mapped = est.map(board_us)
        if mapped is None:
            return None
        value, u = mapped
        reason = self._contradiction(board_us, arrival_us, value, u)
        if reason is None:
            source = "board"
            if self._lagging_since is not None:  # the host behind, or the mapping off: both
                lo = value - u
                value, u = 0.5 * (lo + arrival_us), 0.5 * (arrival_us - lo)
        else:
            self.fallbacks += 1
            self.reason = reason
            lo = arrival_us - span_us - LINK_US
            value, u, source = 0.5 * (lo + arrival_us), 0.5 * (arrival_us - lo), "arrival"
        if self._prev_stamp is not None and value < self._prev_stamp:
            u += self._prev_stamp - value
            value = self._prev_stamp
        if value > arrival_us:
            u += value - arrival_us
            value = arrival_us
        self._prev_stamp = value
        return GuardedStamp(value, u, source)

    def _contradiction(
        self, board_us: float, arrival_us: float, value: float, u: float
    ) -> str | None:
        est = self.estimator
        used = est.counters.used
        prev, self._prev_board = self._prev_board, board_us
        if est.boot_id != self._boot_id:  # the board rebooted: its clock restarted at 0
            self._boot_id, prev = est.boot_id, None
        if prev is not None and board_us <= prev:
            self._doubt_until_used = used
            return "the board's clock stood still or went back while its acquisitions advanced"
        if value - u > arrival_us:
            self._doubt_until_used = used
            return "the board's clock puts an acquisition after its arrival"
        if self._doubt_until_used is not None:
            if used <= self._doubt_until_used:
                return "the board's clock contradicted its acquisitions; no TIME_SYNC answer since"
            self._doubt_until_used = None
            self._lagging_since = None
        if not est.trusted:
            return "the board's TIME_SYNC answers disagree with each other"
        if arrival_us - (value + u) <= MAX_LAG_US:
            self._lagging_since = None
        elif self._lagging_since is None:
            self._lagging_since = arrival_us
        elif arrival_us - self._lagging_since >= LAG_SPAN_US:
            return "the board's clock puts every acquisition of 30 s long before its arrival"
        return None
