"""A virtual board with four CH101 sending I/Q pairs (``sim://?profile=ch101-quad-iq``,
``--samples iq``) end to end: 3-D records timed by the carrier phase, with its covariance;
the same board's amplitudes timed by the envelope."""

from __future__ import annotations

import numpy as np

from tests.headless.test_ranging_boards import _run

TARGET = (20.0, -10.0, 150.0)


def test_four_channel_iq_board_is_timed_by_the_carrier_phase(tmp_path):
    (tmp_path / "iq").mkdir()
    (tmp_path / "env").mkdir()
    iq = _run(tmp_path / "iq", "ch101-quad-iq", "20,-10,150", "--samples", "iq")
    env = _run(tmp_path / "env", "ch101-quad-iq", "20,-10,150")
    assert len(iq) == len(env) == 12
    assert [r["timing"] for r in iq] == ["iq"] * 12
    assert {r["timing"] for r in env} == {"envelope"}
    assert all(r["targets"][0]["timing"] == "iq" for r in iq)
    err_iq = [np.linalg.norm(np.subtract(r["position_mm"], TARGET)) for r in iq]
    err_env = [np.linalg.norm(np.subtract(r["position_mm"], TARGET)) for r in env]
    # the echo model's phase is an exact delay (its noise is on the magnitude): the phase
    # times it to the record's rounding; the envelope to tenths of a millimetre
    assert max(err_iq) < 0.05 and np.median(err_env) > 0.05
    trace = [np.trace(r["targets"][0]["covariance_mm2"]) for r in iq]
    assert max(trace) < min(np.trace(r["targets"][0]["covariance_mm2"]) for r in env) / 20
