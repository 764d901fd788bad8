"""Opt-in checks on a real board: SPIEL_TEST_PORT=/dev/ttyACM0 pytest -m hardware tests/live.

Skipped unless SPIEL_TEST_PORT names a port (any URL `run --port` takes)."""

from __future__ import annotations

import os
import threading

import pytest

from spiel_edge.device import DeviceSession
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol import SCHEMA_HASH, Ping

PORT = os.environ.get("SPIEL_TEST_PORT")
pytestmark = [
    pytest.mark.hardware,
    pytest.mark.skipif(not PORT, reason="set SPIEL_TEST_PORT to a board's port"),
]


def test_board_handshakes_and_streams_clean_acquisitions():
    profile = load_profile(os.environ.get("SPIEL_TEST_PROFILE", "spiel-icra23"))
    stop = threading.Event()
    timer = threading.Timer(30.0, stop.set)
    timer.start()
    try:
        with DeviceSession(PORT, reconnect=False) as board:
            assert board.hello.schema_hash == SCHEMA_HASH, (
                "firmware built against another protocol schema"
            )
            assert board.request(Ping(b"spiel")).data == b"spiel"
            stream = board.start_stream(rate_hz=50, n_samples=profile.acquisition.n_samples)
            assert (stream.n_channels, stream.n_samples) == (
                profile.geometry.n_channels,
                profile.acquisition.n_samples,
            )
            got = []
            for acq in board.acquisitions(stop):
                got.append(acq)
                if len(got) == 100:
                    break
            status = board.stream_status()
            counts = board.counts()
    finally:
        timer.cancel()
    assert len(got) == 100 and status.streaming == 1
    assert counts["lost"] == 0 and counts["crc_errors"] == 0 and counts["overruns"] == 0
    assert all(b.timestamp_us > a.timestamp_us for a, b in zip(got, got[1:], strict=False))
