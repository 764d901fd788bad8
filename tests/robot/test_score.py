"""The virtual robot's scoring (robot/score.py): crossings by cause, like-for-like errors."""

from __future__ import annotations

import numpy as np

from spiel_edge.robot import score


def test_crossings_are_counted_and_failures_split_by_cause():
    n = 40
    ids = [{0: 7, 1: 8} for _ in range(n)]  # mover 0 keeps id 7 throughout
    for k in range(20, n):
        ids[k] = {0: 7}  # mover 1: lost after its crossing at 20
    far = [np.array([[0.0, 0, 0], [500, 0, 0]]) for _ in range(n)]
    events = [(20, 0), (20, 1)]
    reported = [{0, 1}] * 20 + [{0}] * 20  # nobody reports mover 1 after it
    out = score.crossing_ids(ids, events, reported, far)
    assert out == {
        "crossings": 2, "untracked": 0, "kept": 1, "changed": 0, "lost": 1,
        "unreported_after": 1, "near_another": 0,
    }  # fmt: skip
    near = [np.array([[0.0, 0, 0], [50, 0, 0]]) for _ in range(n)]  # movers 50 mm apart
    out = score.crossing_ids(ids, events, reported, near)
    assert (out["near_another"], out["unreported_after"]) == (1, 0)


def test_paired_errors_take_the_same_mover_cycles():
    truths = [np.array([[0.0, 0, 0], [300, 0, 0]])] * 2
    records = [
        {"tracks": [{"position_mm": [3.0, 0, 0]}], "boards": {"a": {"acquisition": 5}}},
        {"tracks": [{"position_mm": [0, 4.0, 0]}], "boards": {"a": {"acquisition": 6}}},
    ]
    primary = np.array([[0, 0], [0, 0]])
    own = {("a", 5): {0: 2.0, 1: 9.0}}  # acquisition 6: the board's tracker had nothing
    out = score.paired_errors(records, truths, primary, ["a"], own)
    assert out["n"] == 1 and out["fused_mean"] == 3.0 and out["own_mean"] == 2.0
