"""The running estimate of the static scene: learns a static scene, keeps a tracked target
out, off by default, bounded on bad input."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import profile_from_dict, profile_to_dict
from spiel_edge.runtime.static_scene import RunningBackground
from tests.core.spiel_csv_fixture import write_spiel_csv


class _Track:
    def __init__(self, position, sigma=2.0):
        self.position_mm = np.asarray(position, float)
        self.covariance_mm2 = np.eye(3) * sigma**2


def _running(profile, window=8, stand_in=None):
    return RunningBackground(profile, window, 4.0, stand_in)


def test_off_by_default_and_on_with_a_window(profile):
    assert RunningBackground.from_profile(profile) is None
    on = profile.replace(track=replace(profile.track, running_background_window=8))
    assert RunningBackground.from_profile(on) is not None


def test_learns_the_static_scene_robustly(profile, rng):
    shape = (profile.geometry.n_channels, profile.acquisition.n_samples)
    static = rng.uniform(0, 500, shape)
    running = _running(profile, stand_in=np.zeros(shape))
    assert np.array_equal(running.background(), np.zeros(shape))  # the stand-in until full
    for k in range(8):
        frame = static + rng.normal(0, 1, shape)
        if k in (2, 5):
            frame[:, 30:34] += 3000.0  # a passing object in a minority of acquisitions
        running.update(frame, [])
    assert np.max(np.abs(running.background() - static)) < 5.0


def test_a_tracked_target_is_not_learnt(profile, rng):
    shape = (profile.geometry.n_channels, profile.acquisition.n_samples)
    static = rng.uniform(0, 500, shape)
    target = np.array([20.0, -10.0, 150.0])
    running = _running(profile, stand_in=static.copy())
    mask = running.track_mask([_Track(target)])
    assert mask.any() and not mask.all()
    g = profile.geometry
    toa = g.echo_paths_mm(target) / profile.mm_per_sample + g.delays()
    for n in range(shape[0]):
        assert mask[n, int(round(toa[n]))]
    echo = np.where(mask, 2000.0, 0.0)
    for _ in range(20):  # the target stands still on a confirmed track
        running.update(static + echo, [_Track(target)])
    assert np.allclose(running.background()[mask], static[mask])
    assert np.allclose(running.background()[~mask], static[~mask])


def test_bad_frames_are_skipped_and_nan_never_comes_out(profile):
    shape = (profile.geometry.n_channels, profile.acquisition.n_samples)
    running = _running(profile, window=2)  # no stand-in: a track's samples are unknown
    running.update(np.full(shape, np.nan), [])
    running.update(np.ones((1, 3)), [])
    assert running.background() is None
    for _ in range(2):
        running.update(np.ones(shape), [_Track([0.0, 0.0, 150.0])])
    assert np.all(np.isfinite(running.background()))
    with pytest.raises(ValueError):
        _running(profile, window=0)


@pytest.mark.parametrize(
    "key,value", [("running_background_window", -1), ("running_background_guard_samples", 1e3)]
)
def test_profile_keys_are_range_checked(profile, key, value):
    data = profile_to_dict(profile)
    data["track"][key] = value
    with pytest.raises(ConfigError, match=key):
        profile_from_dict(data)


def test_replay_track_without_background_feeds_the_running_estimate(subset, tmp_path):
    names = list(subset.names)
    keep = [i for i, n in enumerate(names) if n.startswith("0.0mm_0.0mm_")]
    frames_dir, _ = write_spiel_csv(subset, tmp_path / "rec", keep)
    profile_file = tmp_path / "running.toml"
    builtin = Path(__file__).parents[2] / "spiel_edge/profile/builtin/spiel-icra23.toml"
    profile_file.write_text(
        builtin.read_text().replace(
            "running_background_window = 0", "running_background_window = 4"
        )
    )
    assert "running_background_window = 4" in profile_file.read_text()
    out = tmp_path / "out.ndjson"
    args = ["replay", str(frames_dir), "--profile", str(profile_file), "--track", "-o", str(out)]
    assert main([*args, "--association", "geometric"]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == len(keep) and all("tracks" in r for r in records)
    for r in records:
        for t in r["targets"]:
            assert np.all(np.isfinite(t["position_mm"]))
