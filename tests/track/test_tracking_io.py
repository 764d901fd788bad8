"""Tracking around the tracker: replay/evaluate --track, time order, the scene view, scores."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.outputs.scene_view import CHI2_3DOF_95, Trails, ellipsoid
from spiel_edge.recordings.spiel_csv import Recording
from spiel_edge.runtime.track_records import NOMINAL_PERIOD_S, time_ordered
from spiel_edge.track import Track
from tests.core.spiel_csv_fixture import write_spiel_csv
from tools.bench.track_scene import MoverScore


@pytest.fixture(scope="module")
def folders(subset, tmp_path_factory):
    names = np.array(subset.names)
    keep = [i for i, n in enumerate(names) if n.startswith(("-40.0mm_-40.0mm_", "0.0mm_0.0mm_"))]
    return write_spiel_csv(subset, tmp_path_factory.mktemp("rec"), keep)


def test_replay_track_runs_each_recording_in_time_order(folders, tmp_path):
    frames_dir, bg_dir = folders
    out = tmp_path / "out.ndjson"
    args = ["replay", str(frames_dir), "--background", str(bg_dir), "--track", "-o", str(out)]
    assert main([*args, "--association", "geometric"]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) >= 9
    confirmed = 0
    for r in records:
        run_index = int(r["source"].rsplit("_", 2)[1])
        assert "tracks" in r and "targets" in r
        if run_index == 0:
            assert r["tracks"] == []  # every recording restarts the tracker
        for track in r["tracks"]:  # confirmed on a third hit, never more than one per target
            assert run_index >= 2 and len(r["tracks"]) == 1
            assert 3 <= track["hits"] <= track["age"] <= run_index + 1
            assert np.linalg.norm(np.subtract(track["position_mm"], r["position_mm"])) < 30
            confirmed += 1
    assert confirmed >= len(records) // 4  # static targets: nearly every recording


def test_evaluate_track_reports_the_tracked_error(folders, capsys):
    frames_dir, bg_dir = folders
    args = ["evaluate", str(frames_dir), "--background", str(bg_dir), "--track", "--json"]
    assert main([*args, "--association", "geometric"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    tracked = summary["tracked"]
    assert tracked["acquisitions"] == summary["frames"]  # the same acquisitions (z = 90 left out)
    assert tracked["fixes"] > 0 and 0 < tracked["on_track_share"] < 1
    assert tracked["tracked_mean_mm"] > 0 and tracked["per_acquisition_mean_mm"] > 0


def test_time_order_is_numeric_within_a_recording():
    names = ["a_1_10_frames.csv", "a_1_2_frames.csv", "b_1_0_frames.csv", "a_1_0_frames.csv"]
    timed = list(time_ordered(Recording(n, None, None) for n in names))
    assert [t.recording.source for t in timed] == [
        "a_1_0_frames.csv",
        "a_1_2_frames.csv",
        "a_1_10_frames.csv",
        "b_1_0_frames.csv",
    ]
    assert [t.new_run for t in timed] == [True, False, False, True]
    assert timed[2].t_s == pytest.approx(10 * NOMINAL_PERIOD_S)


def test_ellipsoid_axes_and_orientation(rng):
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    sigmas = np.array([2.0, 5.0, 9.0])
    cov = rotation @ np.diag(sigmas**2) @ rotation.T
    diameters, q = ellipsoid(cov.tolist())
    np.testing.assert_allclose(np.sort(diameters), 2 * sigmas * np.sqrt(CHI2_3DOF_95))
    x, y, z, w = q  # the quaternion's rotation maps each local axis onto a principal axis
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    for axis, diameter in zip(r.T, diameters, strict=True):
        assert axis @ cov @ axis == pytest.approx((diameter / 2) ** 2 / CHI2_3DOF_95, rel=1e-6)
    size, _ = ellipsoid([[np.nan] * 3] * 3)
    assert np.all(np.isfinite(size))


def test_trails_keep_recent_positions_of_live_tracks():
    trails = Trails(length=3)
    for k in range(5):
        shown = trails.update([{"track_id": 1, "position_mm": [k, 0, 0]}])
    assert shown == {1: [[2, 0, 0], [3, 0, 0], [4, 0, 0]]}
    assert trails.update([{"track_id": 2, "position_mm": [0, 0, 1]}]) == {2: [[0, 0, 1]]}


def _track(track_id, pos):
    return Track([track_id, 5, 5, 0], np.r_[pos, 0, 0, 0, np.eye(6).ravel()][None], 0)


def test_mover_score_counts_coverage_and_id_switches():
    score = MoverScore(warmup=1)
    truth = np.array([[0.0, 0, 200], [100.0, 0, 200]])
    for k in range(5):
        ids = (1, 2) if k < 3 else (2, 1)  # the tracks swap targets at k = 3
        tracks = [_track(ids[0], truth[0] + 3), _track(ids[1], truth[1] - 3)]
        tracks = tracks if k != 4 else tracks[:1]
        found = truth + 10 if k != 2 else truth[:1] + 10  # the second target missed at k = 2
        score.add(k, truth, tracks, found)
    s = score.summary()
    assert s["acquisitions_scored"] == 4
    assert s["coverage_per_target"] == [1.0, 0.75] and s["id_switches"] == 2
    assert s["tracked_mean_mm"] == pytest.approx(np.sqrt(27), abs=0.01)
    assert s["per_acquisition_mean_mm"] == pytest.approx(np.sqrt(300), abs=0.01)
    # paired: tracked and found in the same acquisition (not k = 2's second, not k = 4's second)
    assert s["paired_acquisitions"] == 6
    assert s["paired_tracked_mean_mm"] == pytest.approx(np.sqrt(27), abs=0.01)
    assert s["paired_per_acquisition_mean_mm"] == pytest.approx(np.sqrt(300), abs=0.01)


def test_movers_tracked_with_oracle_targets(profile):
    from spiel_edge.pipeline.factory import build_pipeline
    from tools.bench.track_scene import run_movers

    pipeline = build_pipeline(profile, "geometric")
    out = run_movers(pipeline, "sim://?scene=model&movers=2&seed=2", 80, oracle_sigma_mm=5.0)
    assert out["acquisitions_scored"] == 60
    assert out["min_coverage"] >= 0.95 and out["id_switches"] == 0
    assert out["tracked_mean_mm"] < out["per_acquisition_mean_mm"]


def test_tracked_errors_keep_the_static_track_when_one_acquisition_goes_astray():
    """An outlier outside the track's gate counts at its own error in ``tracked`` (the best
    target is on no track) but at the static target's track's in ``static_track``."""
    from types import SimpleNamespace

    from spiel_edge.measure.track_eval import TrackedErrors

    truth = np.zeros(3)
    track = SimpleNamespace(position_mm=np.array([2.0, 0, 0]), hits=5, track_id=0)
    newer = SimpleNamespace(position_mm=np.array([9.0, 0, 0]), hits=1, track_id=1)
    errors = TrackedErrors()
    errors.add(truth, np.array([0, 6.0, 0]), None, [])  # no track yet: the position
    errors.add(truth, np.array([0, 3.0, 0]), track, [track])
    errors.add(truth, np.array([0, 0, 200.0]), None, [newer, track])  # gated out
    got = errors.summary()
    assert got["per_acquisition_mean_mm"] == pytest.approx((6 + 3 + 200) / 3, abs=0.01)
    assert got["tracked_mean_mm"] == pytest.approx((6 + 2 + 200) / 3, abs=0.01)
    assert got["static_track_mean_mm"] == pytest.approx((6 + 2 + 2) / 3, abs=0.01)
    assert got["on_track_share"] == pytest.approx(1 / 3, abs=1e-3)


def test_tracker_is_fed_the_covariance_in_its_own_calibration():
    """The published covariance s^2 L + f^2 I (issue 26's calibration) reaches the tracker as
    0.95^2 L + 8^2 I, the calibration its settings were chosen with; track ids still land on
    the result's own targets."""
    from spiel_edge.pipeline.staged import Result, Target
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime.track_records import (
        TRACKER_COVARIANCE_FLOOR_MM,
        TRACKER_COVARIANCE_SCALE,
        ResultTracker,
        tracker_covariance,
    )

    linear = np.array([[4.0, 1.0, 0.0], [1.0, 9.0, 0.5], [0.0, 0.5, 16.0]])
    published = 7.55**2 * linear + 20.0**2 * np.eye(3)
    expected = TRACKER_COVARIANCE_SCALE**2 * linear + TRACKER_COVARIANCE_FLOOR_MM**2 * np.eye(3)
    np.testing.assert_allclose(tracker_covariance(published, 7.55, 20.0), expected, rtol=1e-12)
    np.testing.assert_allclose(  # the tracker's own calibration passes unchanged
        tracker_covariance(expected, TRACKER_COVARIANCE_SCALE, TRACKER_COVARIANCE_FLOOR_MM),
        expected,
        rtol=1e-12,
    )
    bad = np.full((3, 3), np.nan)  # not the pipeline's: passed on as it is
    stacked = tracker_covariance(np.array([published, bad, expected]), 7.55, 20.0)
    for got, one in zip(stacked, (published, bad, expected), strict=True):  # bit for bit
        assert np.array_equal(got, tracker_covariance(one, 7.55, 20.0), equal_nan=True)
    assert np.isnan(stacked[1]).all()
    profile = load_profile()
    runs = {}
    for scene in (None, profile.scene):
        tracker = ResultTracker(profile.track, scene)
        for k in range(12):
            p = np.array([0.0, 0.0, 200.0 + k])
            s, f = profile.scene.covariance_scale_no_background, profile.scene.covariance_floor_mm
            cov = s**2 * linear + f**2 * np.eye(3)
            target = Target(p, cov, 1.0, [0, 0, 0, 0], 1.0)
            empty = np.zeros((4, 1, 8)), np.zeros(4, dtype=np.int64)
            result = Result(p, None, 1.0, [[]] * 4, [0] * 4, *empty, targets=[target])
            tracks = tracker.update(result, 0.02 * k, captured=False)
        runs[scene is None] = (tracks, target.track_id)
    fed_tracks, fed_id = runs[False]
    assert fed_id is not None and fed_tracks and fed_tracks[0].track_id == fed_id
    # recalibrated: the track's position covariance follows the tracker's scale, not 7.55's
    raw_tracks, _ = runs[True]
    assert np.trace(fed_tracks[0].covariance_mm2) < np.trace(raw_tracks[0].covariance_mm2)
