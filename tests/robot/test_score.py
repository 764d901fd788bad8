"""The virtual robot's scoring (tools/bench/robot_score.py): crossings by cause, like-for-like errors."""

from __future__ import annotations

import numpy as np

from tools.bench import robot_score as score


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


def test_the_oracle_gives_each_mover_its_own_track_from_the_nearest_target():
    from spiel_edge.profile.track_section import TrackSpec
    from spiel_edge.track import Tracker

    rng = np.random.default_rng(3)
    truths, records = [], []
    for k in range(60):  # two movers crossing paths: the targets carry no identity
        a = np.array([-150.0 + 5 * k, 0.0, 300.0])
        b = np.array([150.0 - 5 * k, 10.0, 300.0])
        truths.append(np.array([a, b]))
        seen = [a, b] if k % 7 else [b]  # mover a unseen every 7th cycle
        targets = [
            {"position_mm": (p + rng.normal(0, 2, 3)).tolist(), "covariance_mm2": np.eye(3) * 9}
            for p in seen
        ]
        records.append({"host_time": 0.025 * k, "targets": targets[::-1]})
    out = score.oracle_records(records, truths, lambda: Tracker(TrackSpec()))
    ids, errors = score.coverage(out, truths)
    assert {i[0] for i in ids[10:] if 0 in i} == {1000 * 0 + 0}  # one id for mover a ...
    assert {i[1] for i in ids[10:] if 1 in i} == {1000 * 1 + 0}  # ... another for mover b
    assert sum(len(i) == 2 for i in ids[10:]) >= 45 and np.median(errors) < 5.0
    # a lone target is its nearest mover's only: the other mover's tracker gets nothing
    lone = [
        {
            "host_time": 0.0,
            "targets": [{"position_mm": [0.0, 0, 0], "covariance_mm2": 9 * np.eye(3)}],
        }
    ]
    out = score.oracle_records(
        lone, [np.array([[0.0, 0, 10], [0.0, 0, 30]])], lambda: Tracker(TrackSpec(confirm_hits=1))
    )
    assert [t["track_id"] // 1000 for t in out[0]["tracks"]] == [0]
