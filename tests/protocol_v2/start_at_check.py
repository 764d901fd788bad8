"""STREAM_START's ``start_at_us`` (PROTOCOL.md § 6.4, Capability.START_AT), checked the same way
on the virtual board (tests/protocol_v2/test_v2_start_at.py) and the C firmware
(tests/firmware/test_fw_session.py): a start ahead on the board's clock, one already past
(its grid kept), one too far ahead."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from spiel_edge.errors import DeviceRequestError
from spiel_edge.protocol import ErrorCode

RATE_HZ = 10.0
PERIOD_US = 100_000
TOLERANCE_US = 15_000  # the board stamps when its loop notices the due time (a shared CPU)


def first_stamps(session, n: int) -> list[tuple[int, int]]:
    """(offset from the stream's first index, timestamp_us) of the next ``n`` acquisitions."""
    first = session.stream.first_acquisition
    out = []
    for acq in session.acquisitions(threading.Event()):
        out.append(((acq.index - first) & 0xFFFFFFFF, acq.timestamp_us))
        if len(out) == n:
            break
    session.stop_stream()
    return out


def check_start_at(session) -> None:
    assert session.offers_start_at()
    deadline = time.monotonic() + 5
    while session.board_time_at(time.time()) is None:  # the session syncs at open
        assert time.monotonic() < deadline, "the clocks never synced"
        session.sync_clock()

    # ahead: acquisition 0 at start_at, the next ones on its grid (half a second ahead: with
    # "at once" the first would come that much early)
    start_at = session.board_time_at(time.time()) + 500_000
    session.start_stream(rate_hz=RATE_HZ, n_samples=64, start_at_us=start_at)
    got = first_stamps(session, 4)
    assert got[0][0] == 0
    lag = np.array([ts - (start_at + k * PERIOD_US) for k, ts in got])
    print(f"start_at: fired {lag.tolist()} us after the named times")  # pytest -s shows it
    assert lag.min() >= -2 and np.median(lag) < TOLERANCE_US, lag  # -2: whole us

    # past (the request came late): the grid of start_at is kept, from its first point not past
    now = session.board_time_at(time.time())
    start_at = now - 3 * PERIOD_US - PERIOD_US // 3
    session.start_stream(rate_hz=RATE_HZ, n_samples=64, start_at_us=start_at)
    got = first_stamps(session, 3)
    phase = np.array([(ts - start_at) % PERIOD_US for _, ts in got])
    phase = np.minimum(phase, PERIOD_US - phase)  # distance to the nearest grid point
    assert got[0][1] >= now - TOLERANCE_US and np.median(phase) < TOLERANCE_US, phase

    # too far ahead: refused, no stream
    with pytest.raises(DeviceRequestError) as caught:
        session.start_stream(
            rate_hz=RATE_HZ, start_at_us=session.board_time_at(time.time()) + 61_000_000
        )
    assert caught.value.code == ErrorCode.INVALID and "60 s" in str(caught.value)
