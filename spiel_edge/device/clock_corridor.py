"""The corridor of clock lines a window of two-way time exchanges allows (device/timesync.py
uses it): pure geometry on host and board times, no I/O.

Each exchange bounds the host time of the board's reading from below (the request's send)
and above (the answer's read). The lines host = offset + rate * board above every send and
below every read form a corridor; :func:`corridor` finds its centre line at the rate where it
is widest (golden-section search: the width is concave in the rate), the rates where it
closes, and the envelope of every such line (:class:`Envelope`). Only the convex hulls of the
reads (lower) and the sends (upper) matter, so the searches look at their few vertices.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass

import numpy as np

SEARCH_STEPS = 50  # golden-section steps: the rate to 0.618**50 of 1e-3, about 4e-14


@dataclass(frozen=True, slots=True)
class Corridor:
    """The centre line, centred at (``b0``, ``h0``): host - h0 = offset + rate * (board - b0);
    ``width`` its width at that rate, ``growth`` how far the rate may be off, ``reach`` how
    far that play of the rate moves the line across the window's half-length."""

    b0: float
    h0: float
    offset: float
    rate: float
    width: float
    growth: float
    reach: float


def corridor(
    board: np.ndarray,
    sent: np.ndarray,
    read: np.ndarray,
    wide: tuple[float, float],
    narrow: tuple[float, float] | None = None,
) -> tuple[Corridor | None, Envelope | None]:
    """The centre line of the lines above every ``sent`` and below every ``read`` (host times
    against the ``board`` times, one per exchange), its rate searched within ``narrow`` first
    when given (a prior), then within ``wide``; and the envelope of all those lines. (None,
    None) when no line fits."""
    b0, h0 = float(board.mean()), float(sent.mean())
    board, sent, read = board - b0, sent - h0, read - h0  # centred: no cancellation
    # For any rate, the lowest read - rate * board lies on the lower hull of the reads and the
    # highest send - rate * board on the upper hull of the sends: the searches below look at
    # those few points (a dozen) instead of the whole window (up to 512), once per exchange.
    order = np.argsort(board, kind="stable")
    bx = board[order]
    xs = bx.tolist()
    top = hull(*hull_candidates(bx, read[order], lower=True), lower=True)
    bottom = hull(*hull_candidates(bx, sent[order], lower=False), lower=False)
    low_read, high_sent = lowest(top), highest(bottom)

    def width(rate: float) -> float:  # concave in rate: its maximum is the widest corridor
        return low_read(rate) - high_sent(rate)

    lo, hi = narrow if narrow is not None else wide
    rate = widest(width, lo, hi)
    if width(rate) < 0.0 and narrow is not None:
        lo, hi = wide
        rate = widest(width, lo, hi)
    w = width(rate)
    if w < 0.0:
        return None, None
    # the rates with a corridor at all: how far the rate may be off
    r_lo = root(width, lo, rate) if width(lo) < 0.0 else lo
    r_hi = root(width, hi, rate) if width(hi) < 0.0 else hi
    offset = 0.5 * (low_read(rate) + high_sent(rate))
    growth = max(rate - r_lo, r_hi - rate)
    # Every feasible line's offset at the centre lies within half the width plus the rate's
    # play times the window's half-length (the corridor's walls turn with the rate): a bound
    # for every line the exchanges allow, used to judge answers; stamps use the envelope.
    reach = max(abs(xs[0]), abs(xs[-1])) * growth
    envelope = Envelope(b0, h0, top, bottom, r_lo, r_hi)
    envelope.top_at = {r: low_read(r) for r in (r_lo, r_hi)}
    envelope.bottom_at = {r: high_sent(r) for r in (r_lo, r_hi)}
    return Corridor(b0, h0, float(offset), rate, w, growth, reach), envelope


def lowest(hull: tuple[list[float], list[float]]):
    """rate -> the lowest y - rate * x over the hull's points."""
    points = list(zip(*hull, strict=True))
    return lambda rate: min([y - rate * x for x, y in points])


def highest(hull: tuple[list[float], list[float]]):
    """rate -> the highest y - rate * x over the hull's points."""
    points = list(zip(*hull, strict=True))
    return lambda rate: max([y - rate * x for x, y in points])


class Envelope:
    """The host times that the lines allowed by the exchanges give a board time: no higher
    than the lower convex hull of the reads, no lower than the upper hull of the sends, with
    rates within [r_lo, r_hi] (a relaxation of the corridor, so the range holds whatever line
    is true; within the window it is about the corridor's width, not its width plus the rate's
    play times the window). Beyond the window (or where the hull's slope leaves the rates), the
    extreme rate's line through the hull bounds it. ``top_at``/``bottom_at``: the extreme
    rates' lines under every read / over every send (offsets at 0), set by the caller."""

    def __init__(self, b0, h0, top, bottom, r_lo: float, r_hi: float) -> None:
        self.b0, self.h0, self.r_lo, self.r_hi = b0, h0, r_lo, r_hi
        self.top, self.bottom = top, bottom
        self.top_at: dict[float, float] = {}
        self.bottom_at: dict[float, float] = {}

    def bounds(self, board_us: float) -> tuple[float, float]:
        x = board_us - self.b0
        high = along(self.top, x, self.r_lo, self.r_hi, self.top_at)
        low = along(self.bottom, x, self.r_hi, self.r_lo, self.bottom_at)
        return self.h0 + min(low, high), self.h0 + max(low, high)


def hull_candidates(x: np.ndarray, y: np.ndarray, *, lower: bool, passes: int = 8):
    """The points (sorted by x) that may be on the lower (upper) hull, as lists for
    :func:`hull`: a few vectorised passes drop every point clearly above (below) the chord of
    its two neighbours among those kept, which no hull has as a vertex (a window of 512 jittered
    exchanges keeps a few dozen). Near-collinear points are kept for :func:`hull` to judge,
    so the hull is the one of all the points."""
    keep = np.arange(len(x))
    for _ in range(passes if len(x) > 64 else 0):  # a short window: _hull alone is faster
        if len(keep) < 3:
            break
        a, b, c = keep[:-2], keep[1:-1], keep[2:]
        left = (x[b] - x[a]) * (y[c] - y[a])
        right = (y[b] - y[a]) * (x[c] - x[a])
        cross = left - right
        margin = 1e-9 * (np.abs(left) + np.abs(right))
        out = (cross < -margin) if lower else (cross > margin)
        if not out.any():
            break
        keep = np.concatenate((keep[:1], b[~out], keep[-1:]))
    return x[keep].tolist(), y[keep].tolist()


def hull(xs: list[float], ys: list[float], *, lower: bool) -> tuple[list[float], list[float]]:
    """The lower (or upper) convex hull of points sorted by x (monotone chain)."""
    hx: list[float] = []
    hy: list[float] = []
    for x, y in zip(xs, ys, strict=True):
        if hx and x == hx[-1]:  # the same board time: keep the tighter point
            if (y < hy[-1]) if lower else (y > hy[-1]):
                hx.pop(), hy.pop()
            else:
                continue
        while len(hx) >= 2:
            cross = (hx[-1] - hx[-2]) * (y - hy[-2]) - (hy[-1] - hy[-2]) * (x - hx[-2])
            if (cross <= 0.0) if lower else (cross >= 0.0):
                hx.pop(), hy.pop()
            else:
                break
        hx.append(x)
        hy.append(y)
    return hx, hy


def along(hull, x: float, left_rate: float, right_rate: float, at: dict) -> float:
    """The hull's value at ``x`` where its slope is a rate the exchanges allow; else the line of
    the nearest allowed rate through the hull (``left_rate`` left of the points)."""
    hx, hy = hull
    i = bisect_right(hx, x)
    if i == 0:
        rate = left_rate
    elif i == len(hx):
        rate = right_rate if x > hx[-1] else None
        if rate is None:  # exactly the last point
            return hy[-1]
    else:
        slope = (hy[i] - hy[i - 1]) / (hx[i] - hx[i - 1])
        lo, hi = min(left_rate, right_rate), max(left_rate, right_rate)
        if lo <= slope <= hi:
            return hy[i - 1] + slope * (x - hx[i - 1])
        rate = lo if slope < lo else hi
    return at[rate] + rate * x


def widest(f, lo: float, hi: float) -> float:
    """Golden-section search for the maximum of a concave function on [lo, hi]."""
    g = 0.5 * (math.sqrt(5.0) - 1.0)
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(SEARCH_STEPS):
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return 0.5 * (a + b)


def root(f, outside: float, inside: float) -> float:
    """Bisection between f(outside) < 0 <= f(inside): the edge of the feasible rates."""
    for _ in range(SEARCH_STEPS - 10):  # 0.5**40 of 1e-3
        mid = 0.5 * (outside + inside)
        if f(mid) >= 0.0:
            inside = mid
        else:
            outside = mid
    return inside
