"""Fixtures of the protocol version 2 tests: fresh virtual boards, never shared."""

from __future__ import annotations

import itertools

import pytest

from spiel_edge.sim import protocol_sim

_names = itertools.count()


@pytest.fixture
def sim_url():
    """``sim_url("drift_ppm=200")`` -> a sim:// URL naming a board no other test uses."""
    made: list[str] = []

    def make(query: str = "") -> str:
        url = f"sim://v2test{next(_names)}" + (f"?{query}" if query else "")
        made.append(url)
        return url

    yield make
    for url in made:
        protocol_sim.forget(url)


@pytest.fixture(scope="module")
def posix(tmp_path_factory):
    """The posix C firmware with firmware update (built once per module) and 20 recordings:
    (executable, scans file)."""
    from spiel_edge.data import load_subset
    from tests.firmware.firmware import build_posix
    from tools.release.firmware_scans import write_scans

    d = tmp_path_factory.mktemp("fw-posix-v2")
    exe = build_posix(d / "build")
    scans = write_scans(d / "scans.spas", load_subset().frames[:20], 22000)
    return exe, scans
