"""The tracker's step on preallocated arrays against the step before it
(tests/track/reference_step.py) on random scenes: the same ids, states and counts, bit for bit."""

import numpy as np
import pytest

from spiel_edge.track.assign import INFEASIBLE, assign, assign_into
from spiel_edge.track.layout import (
    DROPPED,
    NEXT_ID,
    STATUS,
    allocate,
    snapshot_meta,
    state_views,
    target_ids,
)
from spiel_edge.track.step import step_kernel
from tests.track import reference_step

# the IMM off (switch probability and static share 0): the CV filter alone, as the reference
PARAMS = np.array([1000.0, 16.27, 9.0, 400.0, 300.0**2, 3, 5, 10, 1.0, 0.0, 0.0])


def _scene(rng, movers, k):
    """Movers (some missed), clutter, now and then a malformed covariance or position."""
    z = [p + rng.normal(0, 4, 3) for p in movers if rng.random() > 0.2]
    z += [rng.uniform([-150, -150, 100], [150, 150, 300]) for _ in range(rng.integers(0, 4))]
    z = np.array(z).reshape(-1, 3)
    r = np.array([np.diag(rng.uniform(4, 400, 3)) for _ in range(len(z))]).reshape(-1, 3, 3)
    if len(z) and k % 7 == 3:
        r[rng.integers(len(z))] = np.nan if k % 2 else -np.eye(3)
    if len(z) and k % 11 == 5:
        z[rng.integers(len(z)), 1] = np.nan
    return np.ascontiguousarray(z[rng.permutation(len(z))]), r


@pytest.mark.parametrize("cap,seed", [(16, 0), (4, 1), (8, 2)])
def test_step_equals_the_reference_on_random_scenes(cap, seed):
    rng = np.random.default_rng(seed)
    arrays = allocate(cap, PARAMS)
    old = [np.zeros((cap, 6)), np.zeros((cap, 6, 6)), np.zeros(cap, np.int8)]
    old += [np.full(cap, -1, np.int64)] + [np.zeros(cap, np.int64) for _ in range(3)]
    old_next, old_counts = np.zeros(1, np.int64), np.zeros(1, np.int64)
    movers = rng.uniform([-100, -100, 150], [100, 100, 250], (6, 3))
    velocity = rng.normal(0, 200, (6, 3))
    confirmed = 0
    for k in range(300):
        dt = 0.02 if k % 50 else 0.0
        movers += velocity * 0.02
        z, r = _scene(rng, movers, k)
        snapshot = step_kernel(*arrays, z, r, dt)
        x, p, meta, counts = state_views(*arrays[:2])
        ref_ids = reference_step._step(*old, old_next, z, r, dt, PARAMS, old_counts)
        assert target_ids(arrays[1], len(z)) == ref_ids.tolist()
        assert np.array_equal(meta[STATUS], old[2])
        live = old[2] != 0
        assert np.array_equal(x[live], old[0][live]) and np.array_equal(p[live], old[1][live])
        for row, value in zip(meta[1:], old[3:], strict=True):
            assert np.array_equal(row[live], value[live])
        assert counts[NEXT_ID] == old_next[0] and counts[DROPPED] == old_counts[0]
        ref_meta, ref_x, ref_p = reference_step._snapshot(*old[2:], old[0], old[1])
        assert snapshot_meta(arrays[1], len(snapshot)) == ref_meta.ravel().tolist()
        assert np.array_equal(snapshot[:, :6], ref_x)
        assert np.array_equal(snapshot[:, 6:].reshape(-1, 6, 6), ref_p)
        confirmed = max(confirmed, len(snapshot))
    assert confirmed >= min(cap, 4)  # the scenes did make tracks
    assert cap > 4 or counts[DROPPED] > 0  # and hit the cap


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (5, 3), (8, 8), (12, 7)])
def test_assignment_into_scratch_equals_the_allocating_one(rng, shape):
    fwork, ints, used = np.zeros((3, 65)), np.zeros((4, 65), np.int64), np.zeros(65, np.bool_)
    cost = np.zeros((64, 64))
    for _ in range(20):
        block = rng.uniform(0, 10, shape)
        block[rng.random(shape) < 0.3] = INFEASIBLE
        cost[: shape[0], : shape[1]] = block
        assign_into(cost, shape[0], shape[1], ints[0], fwork, *ints[1:], used)
        assert np.array_equal(ints[0, : shape[0]], reference_step._assign(block))
        assert np.array_equal(ints[0, : shape[0]], assign(block))
