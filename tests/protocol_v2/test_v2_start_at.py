"""A stream started at a time of the board's clock (STREAM_START ``start_at_us``) on the virtual
board; the same checks run against the C firmware in tests/firmware/test_fw_session.py."""

from __future__ import annotations

import time

import pytest

from spiel_edge.device import DeviceSession
from spiel_edge.errors import DeviceError
from spiel_edge.protocol import StreamStart
from tests.protocol_v2.start_at_check import check_start_at


@pytest.mark.parametrize("drift", [0, 300])
def test_a_stream_starts_at_a_time_of_the_boards_clock(sim_url, drift) -> None:
    with DeviceSession(sim_url(f"drift_ppm={drift}"), reconnect=False) as session:
        check_start_at(session)


@pytest.mark.parametrize("query", ["protocol=1", "start_at=0"])
def test_a_board_without_start_at_is_not_asked(sim_url, query) -> None:
    """A version-1 board, or a version-2 one from before START_AT: no start on its clock."""
    with DeviceSession(sim_url(query), reconnect=False) as session:
        assert not session.offers_start_at()
        with pytest.raises(DeviceError, match="START_AT"):
            session.start_stream(rate_hz=10, start_at_us=1_000_000)


def test_a_restart_after_the_board_came_back_starts_at_once(sim_url) -> None:
    """The request kept for restarts has no start time: the board's clock restarted with it."""
    with DeviceSession(sim_url(), reconnect=False) as session:
        session.sync_clock()
        start = session.board_time_at(time.time()) + 200_000
        session.start_stream(rate_hz=10, start_at_us=start)
        kept = session._stream_request
        session.stop_stream()
    assert isinstance(kept, StreamStart) and kept.start_at_us == 0 and kept.rate_hz == 10
