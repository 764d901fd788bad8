"""Echo picking and delay seeding against straightforward references."""

from __future__ import annotations

import numpy as np

from spiel_edge.calibrate import channel_offsets, pick_echoes


def test_pick_nearest_within_gate_matches_a_loop_reference():
    rng = np.random.default_rng(0)
    cand = rng.uniform(0, 60, (50, 4, 5))
    cand[rng.random(cand.shape) < 0.3] = np.nan
    pred = rng.uniform(0, 60, (50, 4))
    got = pick_echoes(cand, pred, 1.5)
    for i in range(50):
        for n in range(4):
            c = cand[i, n][np.isfinite(cand[i, n])]
            d = np.abs(c - pred[i, n])
            want = c[np.argmin(d)] if c.size and d.min() <= 1.5 else np.nan
            assert np.array_equal(got[i, n], want, equal_nan=True)


def test_channel_offsets_find_the_target_echo_among_clutter():
    rng = np.random.default_rng(1)
    pred = rng.uniform(15, 40, (200, 3))
    true_offset = np.array([2.1, -0.7, 4.0])
    cand = np.full((200, 3, 4), np.nan)
    cand[:, :, 0] = pred + true_offset + rng.normal(0, 0.2, (200, 3))
    cand[:, :, 1:] = pred[:, :, None] + rng.uniform(-8, 8, (200, 3, 3))  # clutter
    assert np.allclose(channel_offsets(cand, pred), true_offset, atol=0.1)


def test_channel_offsets_without_echoes_are_zero():
    assert np.array_equal(channel_offsets(np.full((3, 2, 2), np.nan), np.zeros((3, 2))), [0.0, 0.0])
