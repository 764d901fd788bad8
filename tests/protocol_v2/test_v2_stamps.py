"""Honest stamps on deterministic simulated clocks (spiel_edge/measure/clock_faults.py):
RC-oscillator drift, jitter, and clocks that step, wrap, stop, run backwards or answer
garbage. Each stamp must lie within its stated uncertainty (>= 95 %) and none goes back."""

from __future__ import annotations

import pytest

from spiel_edge.device.stamp_guard import LINK_US, StampGuard
from spiel_edge.device.timesync import TimeSyncEstimator
from spiel_edge.measure.clock_faults import FAULTS, run


@pytest.mark.parametrize(
    "drift_ppm, jitter_us",
    [(0.0, 100.0), (700.0, 1000.0), (-10_000.0, 1000.0), (20_000.0, 5000.0), (-20_000.0, 100.0)],
)
def test_drift_up_to_two_percent_is_within_the_stated_uncertainty(drift_ppm, jitter_us) -> None:
    r = run(drift_ppm=drift_ppm, jitter_us=jitter_us, duration_s=40, seed=1)
    assert r["within_uncertainty"] >= 0.99 and r["backwards"] == 0, r
    assert r["from_arrival"] == 0.0 and r["dropped"] == 0, r
    # honest, not vague: at 1 ms of jitter a stamp's uncertainty is tens of microseconds
    assert r["p50_uncertainty_us"] < 0.25 * jitter_us + 20, r


@pytest.mark.parametrize("fault", FAULTS)
def test_a_bad_clock_never_puts_a_stamp_outside_its_uncertainty_or_backwards(fault) -> None:
    r = run(drift_ppm=10_000.0, jitter_us=1000.0, fault=fault, duration_s=40, seed=2)
    assert r["within_uncertainty"] >= 0.95 and r["backwards"] == 0, r
    assert r["p95_error_us"] < 1.1e6, r  # never 10^13 s: at worst the arrival's bound
    assert r["log_messages"] <= 4, r  # said once (per kind), not per answer


def test_a_clock_that_cannot_be_trusted_falls_back_to_the_arrival_and_says_so() -> None:
    for fault in ("ahead1s", "stuck", "backwards", "wrap2s"):
        r = run(drift_ppm=0.0, fault=fault, duration_s=80, seed=3)
        # answers 1 s ahead look like a host 1 s behind for 30 s (then: the mapping is off)
        assert r["from_arrival"] >= (0.55 if fault == "ahead1s" else 0.45), r
    backlog = run(drift_ppm=0.0, fault="backlog", duration_s=40, seed=3)
    assert backlog["from_arrival"] == 0.0 and backlog["within_uncertainty"] == 1.0, backlog
    clean = run(drift_ppm=0.0, duration_s=40, seed=3)
    assert clean["from_arrival"] == 0.0


def test_the_guard_keeps_stamps_before_their_arrival_and_in_order() -> None:
    est = TimeSyncEstimator()
    for k in range(20):  # the board's clock is the host's minus 1 s, 100 us round trips
        t = 10e6 + k * 0.1e6
        est.add(t - 50, t + 50, t - 1e6, 1)
    guard = StampGuard(est)
    good = guard.stamp(11.9e6 - 1e6, 11.905e6, 2900.0)
    assert good.source == "board" and abs(good.host_us - 11.9e6) < 50
    # the board's clock steps 3 s forward: its acquisition was sampled after it arrived?
    ahead = guard.stamp(12.0e6 + 2e6, 12.005e6, 2900.0)
    assert ahead.source == "arrival" and ahead.host_us <= 12.005e6
    assert ahead.host_us - ahead.uncertainty_us <= 12.005e6 - 2900.0 - LINK_US
    assert "after its arrival" in guard.reason
    # until the estimator keeps a new answer, the board's clock stays in doubt
    again = guard.stamp(12.1e6 + 2e6, 12.105e6, 2900.0)
    assert again.source == "arrival" and again.host_us >= ahead.host_us
    for k in range(5):  # the answers agree on the new offset: a step, the estimator restarts
        t = 12.2e6 + k * 0.1e6
        est.add(t - 50, t + 50, t + 2e6, 1)
    assert est.counters.steps == 1
    back = guard.stamp(12.7e6 + 2e6, 12.705e6, 2900.0)
    assert back.source == "board" and back.host_us >= again.host_us
    assert abs(back.host_us - 12.7e6) <= back.uncertainty_us


def test_a_boot_id_storm_says_so_once_in_a_while() -> None:
    est = TimeSyncEstimator()
    for k in range(60):  # a new boot id every answer for 6 s
        t = 1e6 + k * 0.1e6
        est.add(t - 50, t + 50, 1000.0, boot_id=k)
    said = est.take_messages()
    assert est.counters.resets == 59 and len(said) == 1 and "rebooted" in said[0]
    est.add(40e6 - 50, 40e6 + 50, 1000.0, boot_id=99)  # 30 s later: said again, with a count
    (again,) = est.take_messages()
    assert "58 more like it not shown" in again
