"""The multi-target tracker: against a numpy Kalman filter, ids, birth/deletion, restarts,
the cap and bad input."""

from dataclasses import replace

import numpy as np
import pytest

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.pipeline.staged import Target
from spiel_edge.profile.schema import TrackSpec, load_profile, profile_from_dict, profile_to_dict
from spiel_edge.track import MAX_TARGETS, Tracker
from tests.track import naive

SPEC = TrackSpec()


def _target(pos, sigma=5.0, cov=None):
    cov = np.eye(3) * sigma**2 if cov is None else cov
    return Target(np.asarray(pos, float), np.asarray(cov, float), 1.0, [], 1.0)


def _check_tracks(tracks):
    for t in tracks:
        assert np.all(np.isfinite(t.state)) and np.all(np.isfinite(t.state_covariance))
        assert np.array_equal(t.state_covariance, t.state_covariance.T)
        record = t.record()
        assert set(record) == {
            "track_id",
            "position_mm",
            "velocity_mm_s",
            "covariance_mm2",
            "velocity_covariance_mm2_s2",
            "age",
            "hits",
        }
        assert np.array_equal(
            np.array(record["covariance_mm2"]), np.array(record["covariance_mm2"]).T
        )


def test_single_target_follows_a_numpy_kalman_filter(rng):
    """With the IMM off (no static model) a track is the constant-velocity filter."""
    spec = replace(
        SPEC, confirm_hits=2, confirm_window=3, imm_switch_probability=0.0, imm_static_share=0.0
    )
    tracker = Tracker(spec)
    floor2 = spec.measurement_floor_mm**2
    x = p = None
    for k in range(30):
        t = 0.02 * k
        r = np.diag(rng.uniform(4, 40, 3))
        z = np.array([10.0 + 200 * t, -20.0, 180.0]) + rng.normal(0, 3, 3)
        tracks = tracker.update([_target(z, cov=r)], t)
        r_eff = r + floor2 * np.eye(3)
        if x is None:
            x = np.r_[z, 0, 0, 0]
            p = np.zeros((6, 6))
            p[:3, :3] = r_eff
            p[3:, 3:] = spec.initial_speed_mm_s**2 * np.eye(3)
        else:
            x, p = naive.kf_predict(x, p, 0.02, spec.acceleration_mm_s2)
            x, p = naive.kf_update(x, p, z, r_eff)
        if k >= 1:
            (track,) = tracks
            np.testing.assert_allclose(track.state, x, rtol=1e-9, atol=1e-7)
            np.testing.assert_allclose(track.state_covariance, p, rtol=1e-9, atol=1e-7)
    assert track.track_id == 0 and track.age == 30 and track.hits == 30
    assert track.velocity_mm_s[0] == pytest.approx(200, abs=40)
    _check_tracks(tracks)


def test_a_static_target_is_averaged_like_a_running_mean(rng):
    """Static target, 10 acquisitions of equal noise: with persistent models (switch 0.05) the
    track is about the running mean (the static model wins); with the default (0.3, chosen for
    movers) it still averages far more than the CV filter alone, whose velocity follows the
    noise."""
    truth = np.array([20.0, -30.0, 150.0])
    cv_only = replace(SPEC, imm_switch_probability=0.0, imm_static_share=0.0)
    persistent = replace(SPEC, imm_switch_probability=0.05)
    errors = {"imm": [], "default": [], "cv": [], "mean": []}
    for _ in range(40):  # recordings
        trackers = {"imm": Tracker(persistent), "default": Tracker(SPEC), "cv": Tracker(cv_only)}
        seen = []
        for k in range(10):
            z = truth + rng.normal(0, 10, 3)
            seen.append(z)
            for name, tracker in trackers.items():
                tracks = tracker.update([_target(z, sigma=10.0)], 0.02 * k)
                if k >= SPEC.confirm_hits:
                    errors[name].append(np.linalg.norm(tracks[0].position_mm - truth))
            if k >= SPEC.confirm_hits:
                errors["mean"].append(np.linalg.norm(np.mean(seen, axis=0) - truth))
    imm, default, cv, mean = (np.mean(errors[k]) for k in ("imm", "default", "cv", "mean"))
    assert imm < 1.1 * mean
    assert imm < default < 0.85 * cv


def test_birth_needs_m_of_n_and_sets_track_ids():
    tracker = Tracker(replace(SPEC, confirm_hits=3, confirm_window=5))
    targets = [_target([0, 0, 150])]
    assert tracker.update(targets, 0.0) == [] and targets[0].track_id is None
    assert tracker.update([], 0.02) == []
    assert tracker.update([_target([0, 0, 150])], 0.04) == []
    targets = [_target([0, 0, 150]), _target([100, 0, 300])]
    (track,) = tracker.update(targets, 0.06)
    assert [t.track_id for t in targets] == [0, None]
    assert (track.track_id, track.age, track.hits) == (0, 4, 3)


def test_tracks_are_snapshots_and_tracks_repeats_the_last_update(rng):
    """Track objects keep their values while later updates reuse the step's buffers, and
    ``tracks()`` gives what the last update returned."""
    tracker = Tracker(replace(SPEC, confirm_hits=2))
    kept = None
    for k in range(12):
        targets = [_target([10.0 * k, 0, 150]), _target([-50, 40, 250 - 3.0 * k])]
        tracks = tracker.update(targets, 0.02 * k)
        if k == 5:
            kept = [(t, t.track_id, t.state.copy(), t.state_covariance.copy()) for t in tracks]
    assert len(kept) == 2
    for track, track_id, state, covariance in kept:  # five updates later
        assert track.track_id == track_id
        assert np.array_equal(track.state, state)
        assert np.array_equal(track.state_covariance, covariance)
    again = tracker.tracks()
    assert [t.record() for t in again] == [t.record() for t in tracks]
    assert [t.track_id for t in again] == [0, 1]


def test_a_clutter_target_seen_once_never_becomes_a_track():
    tracker = Tracker()
    for k in range(20):
        targets = [_target([0, 0, 150])] + ([_target([0, 90, 250])] if k == 5 else [])
        tracks = tracker.update(targets, 0.02 * k)
    assert [t.track_id for t in tracks] == [0]


def test_deleted_after_misses_and_ids_are_never_reused():
    tracker = Tracker(replace(SPEC, max_misses=4))
    for k in range(5):
        tracker.update([_target([0, 0, 150])], 0.02 * k)
    for k in range(5, 8):
        assert len(tracker.update([], 0.02 * k)) == 1
    assert tracker.update([], 0.02 * 8) == []
    for k in range(9, 14):
        tracks = tracker.update([_target([0, 0, 150])], 0.02 * k)
    assert [t.track_id for t in tracks] == [1]


def test_crossing_targets_keep_their_ids(rng):
    tracker = Tracker()
    for k in range(100):
        t = 0.02 * k
        a = np.array([-150 + 150 * t, 0, 200.0])  # a and b cross at t = 1 s
        b = np.array([150 - 150 * t, 10, 200.0])
        targets = [_target(a + rng.normal(0, 3, 3)), _target(b + rng.normal(0, 3, 3))]
        if k % 2:
            targets.reverse()  # order carries no identity
        tracker.update(targets, t)
        if k >= 5:
            by_id = {tg.track_id: tg.position_mm[0] for tg in targets}
            assert set(by_id) == {0, 1}
            assert (by_id[0] < by_id[1]) == (t < 1.0) or abs(by_id[0] - by_id[1]) < 20


@pytest.mark.parametrize("jump", [-0.5, 5.0])
def test_time_backwards_or_a_gap_restarts(jump):
    tracker = Tracker(replace(SPEC, max_gap_s=1.0))
    for k in range(5):
        tracks = tracker.update([_target([0, 0, 150])], 0.02 * k)
    assert len(tracks) == 1
    assert tracker.update([_target([0, 0, 150])], 0.08 + jump) == []
    assert tracker.restarts == 1
    for k in range(1, 4):
        tracks = tracker.update([_target([0, 0, 150])], 0.08 + jump + 0.02 * k)
    assert [t.track_id for t in tracks] == [1]


def test_tracks_are_bounded_and_births_counted(rng):
    tracker = Tracker(replace(SPEC, max_tracks=8, confirm_hits=1))
    for k in range(10):
        targets = [_target(p) for p in rng.uniform([-300, -300, 50], [300, 300, 800], (300, 3))]
        tracks = tracker.update(targets, 0.02 * k)
        assert len(tracks) <= 8
    assert tracker.dropped_births > 0
    assert sum(t.track_id is not None for t in targets[MAX_TARGETS:]) == 0


def test_bad_targets_never_give_nan_or_asymmetric_covariance(rng):
    tracker = Tracker(replace(SPEC, confirm_hits=1))
    bad_covs = [
        np.full((3, 3), np.nan),
        -np.eye(3),
        np.array([[10.0, 9.0, 0.0], [-9.0, 10.0, 0.0], [0.0, 0.0, 10.0]]),  # not symmetric
        np.zeros((3, 3)),
        np.diag([1e-30, 1e6, 1.0]),
        "not a matrix",
    ]
    for k in range(60):
        targets = [
            Target(np.array([0.0, 0.0, 150.0]), bad_covs[k % len(bad_covs)], 1.0, [], 1.0),
            Target(np.array([np.nan, 0.0, 150.0]), np.eye(3), 1.0, [], 1.0),
            Target(np.array([1e12, -1e12, 1e12]), np.eye(3) * 1e-12, 1.0, [], 1.0),
        ]
        tracks = tracker.update(targets, 0.02 * k)
        _check_tracks(tracks)
        assert targets[1].track_id is None
    assert any(t.track_id == 0 for t in tracks)
    with pytest.raises(InputError, match="finite"):
        tracker.update([], float("nan"))


def test_track_section_is_validated():
    data = profile_to_dict(load_profile())
    assert profile_from_dict(data).track == load_profile().track
    for key, value in [
        ("max_tracks", 0),
        ("max_tracks", 65),
        ("gate_chi2", 0.5),
        ("max_gap_s", -1.0),
        ("imm_static_noise_mm", -1.0),
        ("imm_switch_probability", 0.6),
        ("imm_static_share", 1.5),
    ]:
        bad = {**data, "track": {**data["track"], key: value}}
        with pytest.raises(ConfigError, match=f"track.{key}"):
            profile_from_dict(bad)
    bad = {**data, "track": {**data["track"], "confirm_hits": 6, "confirm_window": 5}}
    with pytest.raises(ConfigError, match="confirm_hits"):
        profile_from_dict(bad)
    with pytest.raises(ConfigError, match="unknown key"):
        profile_from_dict({**data, "track": {"speed": 1.0}})
