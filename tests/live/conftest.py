"""Fixtures for the live-path tests: fresh virtual boards, never shared between tests."""

from __future__ import annotations

import itertools

import pytest

from spiel_edge.sim import protocol_sim

_names = itertools.count()


@pytest.fixture
def sim_url():
    """``sim_url("ber=1e-4&seed=1")`` -> a sim:// URL naming a board no other test uses."""
    made: list[str] = []

    def make(query: str = "") -> str:
        url = f"sim://test{next(_names)}" + (f"?{query}" if query else "")
        made.append(url)
        return url

    yield make
    for url in made:
        protocol_sim.forget(url)
