"""The echo-level track update prototype (tools/research/echo_track_updates.py): a track that missed is
pulled toward the position whose echo paths it is given, and left alone without them."""

from dataclasses import replace

import numpy as np

from spiel_edge.pipeline.staged import Target
from spiel_edge.profile.schema import TrackSpec, load_profile
from spiel_edge.track import Tracker
from spiel_edge.track.layout import MISSES
from tools.research.echo_track_updates import EchoUpdater


def _confirmed_track_that_missed(at_mm):
    tracker = Tracker(replace(TrackSpec(), confirm_hits=2))
    target = Target(np.asarray(at_mm, float), np.eye(3) * 25.0, 1.0, [], 1.0)
    for k in range(3):
        tracker.update([target], k * 0.02)
    tracker.update([], 0.06)  # a miss: the echo-level update's turn
    return tracker


def test_echoes_pull_a_track_that_missed_toward_their_position():
    profile = load_profile("spiel-icra23")
    updater = EchoUpdater(profile, gate=1.5, sigma=0.3, min_channels=3)
    truth = np.array([10.0, -5.0, 180.0])
    echoes = [[t] for t in updater.toas(truth)[0]]
    tracker = _confirmed_track_that_missed(truth + [0.0, 0.0, 6.0])
    before = np.linalg.norm(tracker._x[0, :3] - truth)
    assert updater.apply(tracker, echoes) == 1
    after = np.linalg.norm(tracker._x[0, :3] - truth)
    assert after < 0.5 * before and tracker._meta[MISSES, 0] == 0
    assert np.allclose(tracker._p[0], tracker._p[0].T)


def test_without_echoes_in_the_gate_nothing_changes():
    profile = load_profile("spiel-icra23")
    updater = EchoUpdater(profile, gate=1.5, sigma=0.3, min_channels=3)
    tracker = _confirmed_track_that_missed([10.0, -5.0, 180.0])
    state = tracker._x.copy()
    far = [[t + 5.0] for t in updater.toas(np.array([10.0, -5.0, 180.0]))[0]]  # 5 samples off
    assert updater.apply(tracker, far) == 0 and updater.apply(tracker, [[]] * 4) == 0
    assert np.array_equal(tracker._x, state)
