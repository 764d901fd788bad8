"""The one slot starter of `run --slot` and `run --robot` (robot/slot_session.start_in_time)."""

from __future__ import annotations

from spiel_edge.robot.slot_keeper import StartAtTrust
from spiel_edge.robot.slot_session import start_in_time


class Session:
    def __init__(self, offers_start_at: bool):
        self.offers = offers_start_at
        self.calls: list = []

    def start_stream_at(self, unix_at, **options):
        self.calls.append(("at", unix_at, options))
        return "named stream" if self.offers else None  # None: no START_AT on this board

    def start_stream(self, **options):
        self.calls.append(("now", options))
        return "host stream"


def test_named_in_the_boards_clock_while_it_keeps_the_time():
    session, waited = Session(True), []
    answer = start_in_time(
        session, StartAtTrust(0.001), 12.5, 40.0, lambda: waited.append(1), n_samples=64
    )
    assert answer == ("named stream", True) and waited == []
    assert session.calls == [("at", 12.5, {"rate_hz": 40.0, "n_samples": 64})]


def test_sent_by_the_host_without_start_at_or_once_the_trust_is_gone():
    session = Session(False)  # the board has no START_AT: the host waits for the moment
    assert start_in_time(session, StartAtTrust(0.001), 1.0, 40.0, lambda: True) == (
        "host stream",
        False,
    )
    assert [c[0] for c in session.calls] == ["at", "now"]
    trust, session = StartAtTrust(0.001), Session(True)
    for _ in range(StartAtTrust.STRIKES):
        trust.landed(0.0, 0.5)  # started half a second off the named time, twice
    assert start_in_time(session, trust, 1.0, 40.0, lambda: True) == ("host stream", False)
    assert [c[0] for c in session.calls] == ["now"]  # not named again


def test_stopping_while_waiting_starts_nothing():
    session = Session(False)
    assert start_in_time(session, StartAtTrust(0.001), 1.0, 40.0, lambda: False) == (None, False)
    assert [c[0] for c in session.calls] == ["at"]
