"""Calibration end to end: synthetic envelopes through the pipeline, and the vendored recordings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from spiel_edge.calibrate import calibrate_frames
from spiel_edge.data import load_subset
from spiel_edge.errors import InputError
from spiel_edge.measure.evaluate import split_by_position
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import Profile
from tests.calibrate.synth import nominal, perturbed_truth, render, target_grid


def test_synthetic_envelopes_through_the_pipeline():
    rng = np.random.default_rng(3)
    profile = nominal()
    start = profile.replace(  # the renderer's delays are where the MEMG mode sits: no re-timing
        geometry=dataclasses.replace(profile.geometry, delay_samples=np.zeros(4)),
        echo_timing=dataclasses.replace(profile.echo_timing, estimator="none"),
    )
    truth = perturbed_truth(profile.geometry, rng)
    targets = target_grid(rng, 300)
    frames, backgrounds = render(
        truth, targets, profile.acquisition.sample_rate_hz, 64, rng, noise=5.0
    )
    cal = calibrate_frames(start, frames, backgrounds, targets)
    g = cal.geometry
    assert len(cal.observations) > 0.95 * cal.expected  # the clutter echo was never picked instead
    assert np.max(np.abs(g.channels_mm - truth.channels_mm)) < 1.0
    assert abs(g.speed_of_sound_m_s / truth.speed_of_sound_m_s - 1) < 0.005
    assert np.max(np.abs(g.delays() - truth.delays())) < 0.05


def test_frames_and_targets_must_agree():
    profile = nominal()
    with pytest.raises(InputError, match="one target position per acquisition"):
        calibrate_frames(profile, np.zeros((3, 4, 64)), None, np.zeros((2, 3)))


def _moved(profile: Profile, seed: int) -> Profile:
    """Each receiver moved 5 mm in a random direction, no delays."""
    g = profile.geometry
    d = np.random.default_rng(seed).normal(size=(4, 3))
    d[0] = 0.0  # channel 0 is the emitter
    d[1:] *= 5.0 / np.linalg.norm(d[1:], axis=1, keepdims=True)
    return profile.replace(
        geometry=dataclasses.replace(g, channels_mm=g.channels_mm + d, delay_samples=np.zeros(4))
    )


def _errors(profile: Profile, frames, backgrounds, truth) -> np.ndarray:
    pipe = build_pipeline(profile, "geometric")
    out = []
    for f, b, t in zip(frames, backgrounds, truth, strict=True):
        r = pipe.process(f, b)
        out.append(np.inf if r.position_mm is None else np.linalg.norm(r.position_mm - t))
    return np.array(out)


def test_real_recordings_calibrated_from_a_moved_geometry_match_the_hand_tuned_profile():
    data = load_subset()
    keep = data.truth_mm[:, 2] != 90.0  # mislabelled layer (see the data README)
    train, val = split_by_position(data.names)
    xy = [tuple(t[:2]) for t in data.truth_mm]
    cal_sel = keep & np.array([k in train for k in xy])
    val_sel = keep & np.array([k in val for k in xy])
    hand = nominal()
    hand_err = _errors(
        hand, data.frames[val_sel], data.backgrounds[val_sel], data.truth_mm[val_sel]
    )
    for seed in (0, 1):
        start = _moved(hand, seed)
        cal = calibrate_frames(
            start, data.frames[cal_sel], data.backgrounds[cal_sel], data.truth_mm[cal_sel]
        )
        moved_err = _errors(
            start, data.frames[val_sel], data.backgrounds[val_sel], data.truth_mm[val_sel]
        )
        err = _errors(
            hand.replace(geometry=cal.geometry),
            data.frames[val_sel],
            data.backgrounds[val_sel],
            data.truth_mm[val_sel],
        )
        assert np.isfinite(err).sum() >= np.isfinite(hand_err).sum()
        mean, hand_mean = err[np.isfinite(err)].mean(), hand_err[np.isfinite(hand_err)].mean()
        assert mean <= 1.05 * hand_mean, (mean, hand_mean)
        assert np.median(err) <= 1.05 * np.median(hand_err)
        assert mean < moved_err[np.isfinite(moved_err)].mean()
