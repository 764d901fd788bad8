"""The device session against the in-process virtual board (sim://)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from spiel_edge.device import DeviceSession
from spiel_edge.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceRequestError,
    DeviceTimeoutError,
)
from spiel_edge.protocol import ErrorCode, ErrorResponse, MsgType, Ping, Pong, StreamStart
from spiel_edge.sim.protocol_sim import device_for_url


def take(session: DeviceSession, n: int, *, stop_after_s: float = 20.0):
    """The next ``n`` acquisitions (the test fails instead of hanging)."""
    stop = threading.Event()
    timer = threading.Timer(stop_after_s, stop.set)
    timer.start()
    got = []
    try:
        for acq in session.acquisitions(stop):
            got.append(acq)
            if len(got) >= n:
                break
    finally:
        timer.cancel()
    assert len(got) == n, f"only {len(got)} of {n} acquisitions in {stop_after_s} s"
    return got


def test_stream_delivers_recordings_with_truth_and_background(sim_url):
    url = sim_url()
    with DeviceSession(url) as session:
        assert session.hello.serial == "SIM0001" and session.identity.serial == "SIM0001"
        session.start_stream(rate_hz=400)
        acqs = take(session, 30)
    scene = device_for_url(url).board.scene
    assert [a.index for a in acqs] == list(range(30))
    for a in acqs:
        np.testing.assert_array_equal(a.samples, scene._frames[a.index])
        np.testing.assert_array_equal(a.background, scene._backgrounds[a.index])
        np.testing.assert_array_equal(a.truth_mm, scene._truth[a.index])
    # acquisitions count when delivered: those still in flight when the stream stops do not
    assert session.counts()["lost"] == 0 and session.counts()["acquisitions"] == 30


def test_bit_errors_damaged_acquisitions_are_counted_and_the_rest_delivered(sim_url):
    url = sim_url("ber=1e-4&seed=5")
    with DeviceSession(url) as session:
        session.start_stream(rate_hz=0)
        acqs = take(session, 1500) + list(session.assembly.ready)  # and those already assembled
        counts = session.counts()
    faults = device_for_url(url).faults.stats
    delivered = {a.index for a in acqs}
    last = max(delivered)
    damaged = {k for k in faults.damaged if k <= last}
    assert damaged, "the fault injector should have hit some acquisitions"
    assert delivered.isdisjoint(damaged)
    assert delivered | damaged == set(range(last + 1))  # every undamaged one was processed
    assert counts["lost"] == len(damaged) == counts["damaged"]
    assert counts["crc_errors"] + counts["framing_errors"] >= len(damaged)


def test_lost_answers_are_retried_and_not_executed_twice(sim_url):
    url = sim_url("drop=0.25&seed=11")
    with DeviceSession(url) as session:
        for _ in range(6):
            session.start_stream(rate_hz=5)
        counters = session.counters
    board = device_for_url(url).board
    assert counters.retries > 0 and board.stats.repeated > 0
    assert board.stats.executed[MsgType.STREAM_START] == 6


def test_request_gives_up_after_three_retries(sim_url):
    url = sim_url("stall_after=1&stall_ms=5000")
    with DeviceSession(url, reconnect=False) as session:
        session.start_stream(rate_hz=100)
        take(session, 1)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match="after 4 tries"):
            session.request(Ping(b"x"), timeout_s=0.05)
        assert time.monotonic() - t0 < 1.0
        assert session.counters.retries == 3 and session.counters.timeouts == 1


def test_error_answers_raise_with_the_device_code(sim_url):
    with DeviceSession(sim_url()) as session:
        assert isinstance(session.request(Ping(b"abc")), Pong)
        with pytest.raises(DeviceRequestError, match="UNSUPPORTED") as info:
            session.request(StreamStart(n_samples=100))  # the replay scene has 64 samples
        assert info.value.code == 8


def test_busy_is_asked_again_with_a_new_sequence_number(sim_url, monkeypatch):
    url = sim_url()
    board = device_for_url(url).board
    execute, seqs = board._execute, []

    def busy_twice(req, now):
        seqs.append(board._request_seq)
        if isinstance(req, Ping) and len(seqs) <= 3:  # seqs[0] is the HELLO
            return ErrorResponse(ErrorCode.BUSY, req.MSG_TYPE)
        return execute(req, now)

    with DeviceSession(url) as session:
        monkeypatch.setattr(board, "_execute", busy_twice)
        assert session.request(Ping(b"ok")).data == b"ok"
    assert len(set(seqs[1:4])) == 3 and session.counters.retries == 0


def test_twenty_unplug_cycles_reconnect_quickly(sim_url):
    url = sim_url("unplug_after=15&unplug_ms=40&unplug_count=20&scene=model&seed=2")
    device = device_for_url(url)
    delays = []
    with DeviceSession(url) as session:
        session.start_stream(rate_hz=500)
        boot = None
        stop = threading.Event()
        timer = threading.Timer(30.0, stop.set)
        timer.start()
        for acq in session.acquisitions(stop):
            if acq.index == 0 and boot is not None:  # first acquisition after a replug
                delays.append(time.monotonic() - device.plug_times[-1])
            boot = acq.index
            if session.counters.reconnects == 20 and acq.index >= 5:
                break
        timer.cancel()
        counts = session.counts()
    assert device.unplugs == 20 and counts["reconnects"] == 20 and counts["disconnects"] == 20
    assert len(delays) == 20 and max(delays) <= 2.0
    assert counts["acquisitions"] >= 20 * 15


def test_the_wait_for_a_replug_is_reported_while_it_lasts(sim_url):
    url = sim_url("unplug_after=5&unplug_ms=400&unplug_count=1&scene=model&seed=3")
    waited = []
    with DeviceSession(url) as session:
        session.on_waiting = waited.append
        session.start_stream(rate_hz=500)
        take(session, 12)
        assert session.counters.reconnects == 1
    assert len(waited) >= 2 and waited == sorted(waited) and waited[-1] < 2.0


def test_without_reconnect_an_unplug_ends_the_stream(sim_url):
    url = sim_url("unplug_after=5&unplug_ms=1000")
    with DeviceSession(url, reconnect=False) as session:
        session.start_stream(rate_hz=500)
        with pytest.raises(DeviceDisconnectedError):
            take(session, 50)


def test_reconnect_gives_up_after_its_timeout(sim_url):
    url = sim_url("unplug_after=5&unplug_ms=60000")
    with DeviceSession(url, reconnect_timeout_s=0.3) as session:
        session.start_stream(rate_hz=500)
        t0 = time.monotonic()
        with pytest.raises(DeviceDisconnectedError, match="did not come back"):
            take(session, 50)
        assert time.monotonic() - t0 < 2.0


def test_a_short_stall_is_ridden_out_by_retries(sim_url, caplog):
    url = sim_url("stall_after=20&stall_ms=600&scene=model")
    with DeviceSession(url, stall_s=0.2) as session:
        session.start_stream(rate_hz=200)
        acqs = take(session, 60)
        assert session.counters.retries >= 1 and session.counters.disconnects == 0
    assert device_for_url(url).board.stats.overruns > 0  # the pings it missed while frozen
    assert [a.index for a in acqs][:20] == list(range(20))
    assert "acquisitions lost in a row (the board froze" in caplog.text  # said, not only counted


def test_a_board_silent_for_longer_is_reopened_and_streams_again(sim_url):
    url = sim_url("stall_after=10&stall_ms=2300&scene=model")
    with DeviceSession(url, stall_s=0.1) as session:
        session.start_stream(rate_hz=200)
        take(session, 30)
        assert session.counters.timeouts == 1
        assert session.counters.disconnects == 1 and session.counters.reconnects == 1


def test_opening_a_missing_or_bad_port_fails_clearly(sim_url, tmp_path):
    with pytest.raises(DeviceDisconnectedError, match="no such device"):
        DeviceSession(f"serial://{tmp_path}/ttyACM9").open()
    with pytest.raises(DeviceError, match="unknown option 'bogus'"):
        DeviceSession(sim_url("bogus=1")).open()
    with pytest.raises(DeviceError, match="unknown port URL scheme"):
        DeviceSession("tcp://localhost:1").open()


def test_a_slow_board_gets_the_scaled_timeout(sim_url, monkeypatch):
    """SPIEL_REQUEST_TIMEOUT_SCALE multiplies each request's own timeout (0.5 s and the wire
    time): an emulated board on a loaded machine gets the time it needs."""
    monkeypatch.setenv("SPIEL_REQUEST_TIMEOUT_SCALE", "3")
    url = sim_url("stall_after=1&stall_ms=5000")
    with DeviceSession(url, reconnect=False) as session:
        session.start_stream(rate_hz=100)
        take(session, 1)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match=r"after 1 tries of 1\.5"):
            session.request(Ping(b"x"), retries=0)
        assert 1.5 <= time.monotonic() - t0 < 3.0


@pytest.mark.parametrize("value", ["0.5", "101", "nan", "fast", "inf"])
def test_a_bad_timeout_scale_is_one_clear_error(sim_url, monkeypatch, value):
    from spiel_edge.errors import ConfigError

    monkeypatch.setenv("SPIEL_REQUEST_TIMEOUT_SCALE", value)
    with pytest.raises(
        ConfigError, match="SPIEL_REQUEST_TIMEOUT_SCALE=.*not a number from 1 to 100"
    ):
        DeviceSession(sim_url(), reconnect=False)
