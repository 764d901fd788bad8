"""The board's clock related to the host's: offset and drift from TIME_SYNC exchanges.

Pure (no I/O, no clock of its own): the session hands it each exchange as three numbers, the
host's clock when the request left (``sent_us``), when the answer's bytes were read
(``received_us``), and the board's clock in the answer (``board_us``). As in PTP's two-way
exchange and MAVLink's TIMESYNC, the board read its clock somewhere inside that round trip, so
one exchange bounds the offset to +-(round trip / 2) about the midpoint. Over a window the
estimator looks for the line host = offset + rate * board that passes above every request's
send time and below every answer's read time (both delays are positive): the feasible lines
form a corridor, and the estimate is its centre line, the rate where the corridor is widest.
A delayed request or answer only loosens one bound, so jitter costs nothing but the fastest
exchanges' delays, which shrink as the window fills (with 1 ms of uniform jitter and a few
hundred exchanges, a few us) -- where a least-squares line through the midpoints keeps the
spread of their asymmetries. When no line fits every exchange (a clock that wandered inside
the window), the estimator falls back to a least-squares line through the midpoints of the
exchanges with the shortest round trips.

Outliers: an answer whose round trip is long, whose board time goes backwards, or that lies
far from the current line is dropped and counted; several in a row that agree with each other
mean the board's clock was stepped, and the estimator starts again from them. A new boot id
(the board reset) starts it again at once, keeping the measured drift: a board's oscillator
does not change with a reset, so the first exchange after it is already good to its round trip.

``map(board_us)`` gives the host time and its uncertainty (about 95 %): with fewer than
``MIN_FIT`` exchanges the hard bound of the best exchange (half its round trip plus the
drift bound times the time since), then the fit's prediction error.

Drift: RC oscillators run 1-2 % off (crystals 20-100 ppm), so the rate is searched within
+-3 %. Absurd answers (negative, beyond 2**53 us -- 285 years -- u64::MAX, not finite) are
dropped before anything else. ``trusted`` says whether the answers agree with each other:
two or more rejected in a row, or more than a third of the last 16 rejected (an answer that
alternates between two clocks, a clock that wraps or runs backwards), and the board's clock
is not to be trusted until the estimator restarts or its answers agree again; the stamps
then fall back to the host's arrival time (:class:`spiel_edge.device.stamp_guard.StampGuard`).
Each kind of message is said once and then at most every ``SAY_EVERY_US`` with the count of
those not said: a boot-id storm or a garbage-spewing board cannot flood the log.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.device.clock_corridor import Envelope, corridor

__all__ = ["ClockEstimate", "SyncCounters", "SyncSample", "TimeSyncEstimator"]

MAX_DRIFT = 0.03  # |board rate / host rate - 1| at most: RC oscillators 1-2 %, crystals 1e-4
MAX_BOARD_US = float(2**53)  # a board time beyond this (285 years; u64::MAX) is garbage
HISTORY = 16  # the last answers' fates, for ``trusted``
MAX_REJECTED = 1 / 3  # more of the last HISTORY rejected than this: the answers disagree
SAY_EVERY_US = 30e6  # a kind of message said again at most this often (with a count)
MAX_RTT_US = 200_000.0  # a round trip longer than this tells nothing useful
WINDOW = 512  # exchanges kept for the fit
MIN_FIT = 8  # exchanges before the fit replaces the best single exchange
BEST_FRACTION = 0.12  # the fit uses this fraction of the window, shortest round trips first
SIGMAS = 3.5  # the stated uncertainty: this many standard errors of the fit's prediction
OUTLIER_FLOOR_US = 2_000.0  # an answer this far (and 8 uncertainties) off the line is an outlier
STEP_AFTER = 5  # consecutive agreeing outliers: the board's clock was stepped
RESOLUTION_US = 2.0  # both clocks' resolution (whole us on the wire) on top of half a round trip
FAST_UNTIL = 64  # exchanges in the window before the session syncs at its normal period
FAST_PERIOD_S = 0.1


@dataclass(frozen=True, slots=True)
class SyncSample:
    sent_us: float  # host clock when the request was written
    received_us: float  # host clock when the answer was read
    board_us: float  # the board's clock in the answer

    @property
    def rtt_us(self) -> float:
        return self.received_us - self.sent_us

    @property
    def mid_us(self) -> float:
        return 0.5 * (self.sent_us + self.received_us)


@dataclass(frozen=True, slots=True)
class ClockEstimate:
    """host_us = host_ref_us + rate * (board_us - board_ref_us), with the uncertainty model."""

    board_ref_us: float
    host_ref_us: float
    rate: float  # host us per board us (1 - drift)
    base_uncertainty_us: float  # at board_ref_us
    growth: float  # extra uncertainty per us away from board_ref_us (drift not known better)
    fitted: bool  # False: one exchange's hard bound

    def map(self, board_us: float) -> tuple[float, float]:
        dt = board_us - self.board_ref_us
        host = self.host_ref_us + self.rate * dt
        return host, self.base_uncertainty_us + self.growth * abs(dt)


@dataclass
class SyncCounters:
    exchanges: int = 0  # answers offered
    used: int = 0  # answers kept
    long_rtt: int = 0  # dropped: round trip too long (or negative)
    backwards: int = 0  # dropped: the board's clock went backwards
    outliers: int = 0  # dropped: far from the current estimate
    absurd: int = 0  # dropped: a board time no clock can read (garbage, u64::MAX)
    steps: int = 0  # the board's clock was stepped: estimator restarted
    resets: int = 0  # the board rebooted (new boot id): estimator restarted
    messages: list[str] = field(default_factory=list)  # what happened, for the caller to log

    def as_dict(self) -> dict[str, int]:
        return {k: v for k, v in self.__dict__.items() if isinstance(v, int)}


class TimeSyncEstimator:
    def __init__(self) -> None:
        self.counters = SyncCounters()
        self.boot_id: int | None = None
        self.estimate: ClockEstimate | None = None
        self._samples: deque[SyncSample] = deque(maxlen=WINDOW)
        self._suspects: list[SyncSample] = []
        self._rate: float | None = None  # the current fit's rate (host us per board us)
        self._rate_sd = MAX_DRIFT
        self._prior: tuple[float, float] | None = None  # (rate, sd) measured before a reset
        self._bound: ClockEstimate | None = None  # the best exchange's hard bound
        self._fitted: ClockEstimate | None = None  # the line through the window
        self._envelope: Envelope | None = None  # every line the window allows
        self._history: deque[bool] = deque(maxlen=HISTORY)  # recent answers: kept or not
        self._said: dict[str, tuple[float, int]] = {}  # message kind -> (said at, not said)
        self.consistent = True  # False: the last fit found no line within every round trip

    # --- input -------------------------------------------------------------------------

    def reset(self, boot_id: int | None = None) -> None:
        """Forget the offset (the board rebooted); the measured drift is kept as a prior."""
        if self._rate is not None and self.estimate is not None and self.estimate.fitted:
            self._prior = (self._rate, self._rate_sd)
        self.boot_id = boot_id
        self._samples.clear()
        self._suspects.clear()
        self._history.clear()
        self.estimate = self._bound = self._fitted = None
        self._envelope = None

    def add(self, sent_us: float, received_us: float, board_us: float, boot_id: int) -> bool:
        """One exchange; False (and a counter, and a message) when it was not used."""
        c = self.counters
        c.exchanges += 1
        now = float(received_us)
        if self.boot_id is not None and boot_id != self.boot_id:
            c.resets += 1
            self._say(
                "reset", f"the board rebooted (boot id {boot_id:08x}): clock sync restarted", now
            )
            self.reset(boot_id)
        self.boot_id = boot_id
        s = SyncSample(float(sent_us), float(received_us), float(board_us))
        if not 0.0 <= s.rtt_us <= MAX_RTT_US:
            c.long_rtt += 1
            return False
        if not (math.isfinite(s.board_us) and 0.0 <= s.board_us <= MAX_BOARD_US):
            c.absurd += 1
            self._history.append(False)
            self._say(
                "absurd", f"TIME_SYNC answer with an absurd board time ({board_us!r}): ignored", now
            )
            return False
        last = self._samples[-1] if self._samples else None
        if last is not None and s.board_us < last.board_us - last.rtt_us - s.rtt_us:
            c.backwards += 1
            self._say(
                "backwards",
                f"TIME_SYNC answer goes backwards ({(last.board_us - s.board_us) / 1e6:.6f} s "
                "before the previous one): ignored",
                now,
            )
            return self._suspect(s)
        if self.estimate is not None:
            host, u = self.estimate.map(s.board_us)
            off = abs(s.mid_us - host)
            if off > max(8.0 * u, OUTLIER_FLOOR_US) + 0.5 * s.rtt_us:
                c.outliers += 1
                self._say(
                    "outlier",
                    f"TIME_SYNC answer {(host - s.mid_us) / 1e6:+.6f} s off the board's clock "
                    "estimate: ignored",
                    now,
                )
                return self._suspect(s)
        self._suspects.clear()
        self._samples.append(s)
        self._history.append(True)
        c.used += 1
        self._refit()
        return True

    @property
    def trusted(self) -> bool:
        """An estimate exists and the recent answers agree with it (see the module's text)."""
        if self.estimate is None or len(self._suspects) >= 2:
            return False
        h = self._history
        return len(h) < 8 or h.count(False) <= MAX_REJECTED * len(h)

    def _say(self, kind: str, text: str, now_us: float) -> None:
        """A message once, then at most every SAY_EVERY_US per kind, with how many were not."""
        at, quiet = self._said.get(kind, (-math.inf, 0))
        if now_us - at < SAY_EVERY_US:
            self._said[kind] = (at, quiet + 1)
            return
        if quiet:
            text += f" ({quiet} more like it not shown)"
        self._said[kind] = (now_us, 0)
        self.counters.messages.append(text)

    def _suspect(self, s: SyncSample) -> bool:
        """Outliers in a row that agree with each other: the board's clock was stepped."""
        suspects = self._suspects
        if suspects:
            prev = suspects[-1]
            # consecutive suspects must agree with each other (same offset within their rtts)
            if abs((s.mid_us - s.board_us) - (prev.mid_us - prev.board_us)) > (
                OUTLIER_FLOOR_US + s.rtt_us + prev.rtt_us
            ):
                suspects.clear()
        suspects.append(s)
        self._history.append(False)
        if len(suspects) < STEP_AFTER:
            return False
        self.counters.steps += 1
        self._say(
            "step",
            f"the board's clock was stepped ({STEP_AFTER} answers in a row agree on a new "
            "offset): clock sync restarted",
            s.received_us,
        )
        kept = list(suspects)
        self._samples.clear()
        self._suspects.clear()
        self._history.clear()
        self._history.extend([True] * len(kept))
        self._samples.extend(kept)
        self.counters.used += len(kept)
        self._refit()
        return True

    # --- the estimate ------------------------------------------------------------------

    def _refit(self) -> None:
        self._least_squares()
        self.consistent = True
        self._envelope = None
        if self._fitted is not None:
            corridor, self._envelope = fit_corridor(list(self._samples), self._prior)
            self.consistent = corridor is not None
            if corridor is not None:
                self.estimate = self._fitted = corridor
                self._rate = corridor.rate
                self._rate_sd = min(max(corridor.growth / SIGMAS, 1e-9), MAX_DRIFT)

    def _least_squares(self) -> None:
        samples = list(self._samples)
        best = min(samples, key=lambda s: s.rtt_us)
        prior_rate, prior_sd = self._prior if self._prior is not None else (1.0, MAX_DRIFT)
        # the hard bound of the best exchange; the rate known before a reset, if any
        growth = min(SIGMAS * prior_sd, MAX_DRIFT)
        bound = ClockEstimate(
            best.board_us, best.mid_us, prior_rate, 0.5 * best.rtt_us + RESOLUTION_US, growth, False
        )
        self.estimate, self._bound, self._fitted = bound, bound, None
        if len(samples) < MIN_FIT:
            return
        k = max(MIN_FIT, int(len(samples) * BEST_FRACTION))
        chosen = sorted(samples, key=lambda s: s.rtt_us)[:k]
        x = [s.board_us for s in chosen]
        y = [s.mid_us for s in chosen]
        n = len(chosen)
        xm, ym = sum(x) / n, sum(y) / n
        sxx = sum((xi - xm) ** 2 for xi in x)
        fit_rate = (
            sum((xi - xm) * (yi - ym) for xi, yi in zip(x, y, strict=True)) / sxx
            if sxx >= 1e6
            else prior_rate
        )
        resid = [yi - (ym + fit_rate * (xi - xm)) for xi, yi in zip(x, y, strict=True)]
        sd = math.sqrt(sum(r * r for r in resid) / max(n - 2, 1))
        fit_sd = sd / math.sqrt(sxx) if sxx >= 1e6 else MAX_DRIFT
        # the fit's rate and the prior's (from before a reset), weighted by their variances:
        # a few seconds after a reset the prior is far better than the short window's slope
        w_fit, w_prior = 1.0 / max(fit_sd, 1e-9) ** 2, 1.0 / max(prior_sd, 1e-9) ** 2
        rate = (fit_rate * w_fit + prior_rate * w_prior) / (w_fit + w_prior)
        rate_sd = math.sqrt(1.0 / (w_fit + w_prior))
        rate = min(max(rate, 1.0 - MAX_DRIFT), 1.0 + MAX_DRIFT)
        resid = [yi - (ym + rate * (xi - xm)) for xi, yi in zip(x, y, strict=True)]
        sd = math.sqrt(sum(r * r for r in resid) / max(n - 2, 1))
        self._rate, self._rate_sd = rate, min(max(rate_sd, 1e-8), MAX_DRIFT)
        # about 95 %: SIGMAS standard errors of the line's prediction at its centre, growing
        # with the rate's standard error away from it
        small = 1.0 + 4.0 / n  # few exchanges: a wider interval (Student's t, roughly)
        # No line passes within every round trip here (the corridor was empty): the answers
        # contradict each other (a wandering clock, or a board answering from two clocks), so
        # the line's own standard error would claim what the answers cannot tell. The spread
        # of the answers themselves is stated instead.
        base = small * SIGMAS * sd + 1.0
        fitted = ClockEstimate(xm, ym, rate, base, small * SIGMAS * self._rate_sd, True)
        self.estimate = self._fitted = fitted

    def map(self, board_us: float) -> tuple[float, float] | None:
        """(host_us, uncertainty_us) of a board time, or None before the first exchange.

        The fit's value once there is one; its uncertainty the fit's own, or, while that is
        still wider, the hard bound's widened by the distance between the two values (the
        truth lies within the bound, so within that of the fit's value)."""
        if self.estimate is None:
            return None
        fitted, bound = getattr(self, "_fitted", None), getattr(self, "_bound", None)
        if fitted is None or bound is None:
            return self.estimate.map(board_us)
        value, u_fit = fitted.map(board_us)
        if self._envelope is not None:  # the exact range of the lines that fit: its middle
            lo, hi = self._envelope.bounds(board_us)
            value, u_fit = 0.5 * (lo + hi), 0.5 * (hi - lo)
        hard, u_bound = bound.map(board_us)
        return value, min(u_fit, u_bound + abs(value - hard))

    def unmap(self, host_us: float) -> float | None:
        """The board time that :meth:`map` takes to ``host_us`` (the line's value), or None
        before the first exchange."""
        line = getattr(self, "_fitted", None) or self.estimate
        if line is None:
            return None
        return line.board_ref_us + (host_us - line.host_ref_us) / line.rate

    def interval(self, normal_s: float) -> float:
        """The time to the next exchange: faster (0.1 s) while the window is short."""
        return min(normal_s, FAST_PERIOD_S) if len(self._samples) < FAST_UNTIL else normal_s

    def take_messages(self) -> list[str]:
        out, self.counters.messages = self.counters.messages, []
        return out


def fit_corridor(
    samples: list[SyncSample], prior: tuple[float, float] | None
) -> tuple[ClockEstimate | None, Envelope | None]:
    """The exchanges' corridor (device/clock_corridor.py) as a clock line: sends and reads
    widened by the clocks' resolution, the rate within +-MAX_DRIFT (within SIGMAS of
    ``prior``, the rate and its deviation measured before a reset, first); and the envelope
    of every allowed line. (None, None) when no line fits."""
    board = np.array([x.board_us for x in samples])
    sent = np.array([x.sent_us for x in samples]) - RESOLUTION_US
    read = np.array([x.received_us for x in samples]) + RESOLUTION_US
    wide = (1.0 - MAX_DRIFT, 1.0 + MAX_DRIFT)
    narrow = None
    if prior is not None:  # the rate measured before a reset narrows the search
        narrow = (
            max(wide[0], prior[0] - SIGMAS * prior[1]),
            min(wide[1], prior[0] + SIGMAS * prior[1]),
        )
    found, envelope = corridor(board, sent, read, wide, narrow)
    if found is None:
        return None, None
    base = 0.5 * found.width + found.reach + RESOLUTION_US
    line = ClockEstimate(found.b0, found.h0 + found.offset, found.rate, base, found.growth, True)
    return line, envelope
