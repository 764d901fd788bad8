"""``run`` tracks by default; the virtual board's movers reach the host with their truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.device.acquisitions import StreamAssembly
from spiel_edge.device.annotation import TARGETS_TYPE, TruthTargets, encode_truth_targets
from spiel_edge.errors import ConfigError
from spiel_edge.link.sim_options import SimOptions
from spiel_edge.protocol.framing import Frame
from spiel_edge.sim.movers import HALF_RANGE_MM, MAX_TOP_SPEED_MM_S, MoverPaths


def _records(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_run_tracks_movers_and_carries_every_truth(sim_url, tmp_path):
    out = tmp_path / "out.ndjson"
    url = sim_url("scene=model&movers=2&seed=3")
    assert main(["run", "--port", url, "--frames", "25", "--rate", "200", "-o", str(out)]) == 0
    recs = _records(out)
    assert all(len(r["truth_targets_mm"]) == 2 for r in recs)
    assert all("tracks" in r and "targets" in r for r in recs)
    tracked = [r for r in recs[5:] if r["tracks"]]
    assert len(tracked) >= 15
    nearest = []
    for r in tracked:
        for t in r["tracks"]:
            assert set(t) == {
                "track_id",
                "position_mm",
                "velocity_mm_s",
                "covariance_mm2",
                "velocity_covariance_mm2_s2",
                "age",
                "hits",
            }
            cov = np.array(t["covariance_mm2"])
            assert np.array_equal(cov, cov.T) and np.all(np.isfinite(cov))
            nearest.append(
                min(np.linalg.norm(np.subtract(t["position_mm"], p)) for p in r["truth_targets_mm"])
            )
    assert np.mean(np.array(nearest) < 40) >= 0.8  # a coasting track may lag a turn


def test_run_no_track_leaves_tracks_out(sim_url, tmp_path):
    out = tmp_path / "out.ndjson"
    url = sim_url("scene=model")
    assert main(["run", "--port", url, "--frames", "5", "--no-track", "-o", str(out)]) == 0
    assert all("tracks" not in r and "truth_targets_mm" in r for r in _records(out))


def test_movers_are_smooth_bounded_and_in_front(rng):
    paths = MoverPaths(4, seed=7)
    t = np.arange(0.0, 30.0, 0.01)
    pos = np.array([paths.positions(x) for x in t])
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=2) / 0.01
    assert speed.max() <= MAX_TOP_SPEED_MM_S * 1.01
    assert np.all(np.abs(pos[..., :2]) <= HALF_RANGE_MM[:2] + 1e-9) and np.all(pos[..., 2] > 100)
    ranges = np.linalg.norm(pos, axis=2)
    assert np.count_nonzero(np.diff(np.sign(ranges[:, 0] - ranges[:, 1]))) >= 2  # they cross
    assert np.array_equal(MoverPaths(4, seed=7).positions(1.5), paths.positions(1.5))
    with pytest.raises(ConfigError, match="movers"):
        SimOptions.from_url("sim://?scene=model&movers=9")


def test_truth_targets_annotation_round_trip_and_bad_payloads():
    truth = np.array([[1.0, 2.0, 150.0], [-40.0, 5.5, 220.0]])
    wire = encode_truth_targets(7, truth)
    assert wire[0] == 0
    note = TruthTargets.unpack(TruthTargets(7, truth.astype("<f4").tobytes()).pack())
    np.testing.assert_allclose(note.positions_mm(), truth, atol=1e-4)
    stream = StreamAssembly()
    bad = TruthTargets(7, b"\x00" * 13).pack()  # not whole (x, y, z) rows
    assert stream.feed(Frame(TARGETS_TYPE, 0, 0, 7, bad), 0)
    nan = TruthTargets(7, np.full(3, np.nan, "<f4").tobytes()).pack()
    assert stream.feed(Frame(TARGETS_TYPE, 0, 0, 7, nan), 0)
    assert stream.bad_messages == 2
    empty = TruthTargets(8, b"").pack()  # a scene without targets now: no targets, not bad
    assert stream.feed(Frame(TARGETS_TYPE, 0, 0, 8, empty), 0)
    assert stream.bad_messages == 2
    assert TruthTargets.unpack(empty).positions_mm().shape == (0, 3)
