"""The corridor search over the hulls' points (issue 39: one refit per TIME_SYNC exchange
cost ~1 ms of a 50/s stream's CPU) finds what a search over every exchange of the window
finds: the same rate, offset, width and envelope."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.device import clock_corridor as cc
from spiel_edge.device.timesync import MAX_DRIFT, RESOLUTION_US, SyncSample, fit_corridor


def _window(seed: int, n: int, jitter_us: float, drift: float) -> list[SyncSample]:
    rng = np.random.default_rng(seed)
    sent = np.cumsum(rng.choice([3_000.0, 100_000.0, 250_000.0], n)) + 1e6
    rtt = 200.0 + rng.random(n) * jitter_us
    board = (sent + rtt * rng.random(n)) * drift + 5e6
    return [SyncSample(s, s + r, b) for s, r, b in zip(sent, rtt, board, strict=True)]


def _reference_width(samples: list[SyncSample]):
    """width(rate) over every exchange, as before the hulls (numpy over the whole window)."""
    board = np.array([x.board_us for x in samples])
    sent = np.array([x.sent_us for x in samples]) - RESOLUTION_US
    read = np.array([x.received_us for x in samples]) + RESOLUTION_US
    b0, h0 = float(board.mean()), float(sent.mean())
    board, sent, read = board - b0, sent - h0, read - h0
    return lambda r: float(np.min(read - r * board) - np.max(sent - r * board))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    ("n", "jitter_us", "drift"), [(12, 50.0, 1.0), (512, 1000.0, 1.0001), (300, 20_000.0, 0.98)]
)
def test_the_hulls_give_the_whole_windows_corridor(seed, n, jitter_us, drift) -> None:
    samples = _window(seed, n, jitter_us, drift)
    line, envelope = fit_corridor(samples, None)
    assert line is not None and envelope is not None
    width = _reference_width(samples)
    lo, hi = 1.0 - MAX_DRIFT, 1.0 + MAX_DRIFT
    rate = cc.widest(width, lo, hi)  # the search on the whole window
    assert line.rate == rate
    for r in (lo, hi, rate, envelope.r_lo, envelope.r_hi, 0.5 * (lo + rate)):
        lowest = cc.lowest(envelope.top)(r)
        highest = cc.highest(envelope.bottom)(r)
        assert lowest - highest == width(r)
    assert envelope.r_lo < rate < envelope.r_hi
    assert width(envelope.r_lo) >= 0.0 and width(envelope.r_hi) >= 0.0


def test_no_line_fits_contradicting_exchanges() -> None:
    good = _window(1, 40, 100.0, 1.0)
    # an answer 50 ms away from the others, with a short round trip: no line passes it all
    bad = SyncSample(good[20].sent_us, good[20].sent_us + 300.0, good[20].board_us + 50_000.0)
    assert fit_corridor([*good, bad], None) == (None, None)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("lower", [True, False])
def test_the_candidates_keep_every_hull_vertex(seed, lower) -> None:
    """Dropping the points above (below) their neighbours' chord first gives the same hull."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(65, 600))
    x = np.sort(rng.choice(np.arange(0.0, 4e8, 1e5), n))
    k = int(rng.integers(1, n - 1))
    x[k] = x[k - 1]  # a repeated board time
    y = 1.0001 * x + rng.random(n) * (1e3 if seed % 2 else 3e4)
    assert cc.hull(*cc.hull_candidates(x, y, lower=lower), lower=lower) == cc.hull(
        x.tolist(), y.tolist(), lower=lower
    )
    kept = cc.hull_candidates(x, y, lower=lower)[0]
    assert len(kept) < n // 2  # it does drop most of a jittered window
