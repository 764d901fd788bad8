"""The tracker's buffered path (targets written into the step's arrays, ``step_buffered``)
against ``measurements`` and ``step_kernel``: the same numbers, bit for bit."""

import numpy as np
import pytest

from spiel_edge.pipeline.staged import Target
from spiel_edge.track.layout import allocate, measurement_views, snapshot_rows, target_ids
from spiel_edge.track.step import step_buffered, step_kernel
from spiel_edge.track.tracker import Tracker, measurements

PARAMS = np.array([2000.0, 16.27, 1.0, 400.0, 300.0**2, 3, 5, 10, 4.0, 0.05, 0.5])

ODD = [
    (np.array([1.0, 2.0]), None),  # wrong length, no covariance
    ([5.0, 6.0, 200.0], 3.0),  # a list, a scalar
    (np.array([[5.0, 6.0, 200.0]]), np.eye(3)[None]),  # extra leading axes
    (np.array([np.nan, 0.0, 100.0]), np.full((3, 3), np.nan)),
]


@pytest.mark.parametrize("odd", [None, *range(len(ODD))])
def test_written_measurements_are_those_of_measurements(odd):
    rng = np.random.default_rng(3)
    targets = [Target(rng.normal(0, 100, 3), np.diag(rng.uniform(5, 50, 3)), 1.0, [], 1.0)]
    targets += [Target(rng.normal(0, 100, 3), np.eye(3) * 9.0, 1.0, [], 1.0)]
    if odd is not None:
        targets.insert(1, Target(*ODD[odd], 1.0, [], 1.0))
    tracker = Tracker()
    tracker._write_measurements(targets)
    z, r = measurements(targets)
    m = len(targets)
    np.testing.assert_array_equal(tracker._z[:m], z)
    np.testing.assert_array_equal(tracker._r[:m], r)


def test_all_column_positions_take_the_general_path():
    targets = [
        Target(np.arange(3.0).reshape(3, 1) + k, np.eye(3).ravel(), 1.0, [], 1.0) for k in range(3)
    ]
    tracker = Tracker()
    tracker._write_measurements(targets)
    z, r = measurements(targets)
    np.testing.assert_array_equal(tracker._z[:3], z)
    np.testing.assert_array_equal(tracker._r[:3], r)


def test_buffered_step_is_the_step():
    rng = np.random.default_rng(5)
    a, b = allocate(6, PARAMS), allocate(6, PARAMS)
    zb, rb = measurement_views(b[0])
    for k in range(200):
        m = int(rng.integers(0, 10))
        z = rng.normal(0, 60, (m, 3)) + 200.0
        r = np.eye(3) * rng.uniform(5, 60, (m, 1, 1))
        zb[:m], rb[:m] = z, r
        dt = 0.02 if k else 0.0
        snap_a = step_kernel(*a, z, r, dt)
        snap_b = snapshot_rows(b[0], step_buffered(*b, m, dt))
        np.testing.assert_array_equal(snap_a, snap_b)
        assert target_ids(a[1], m) == target_ids(b[1], m)
    for x, y in zip(a, b, strict=True):
        n = len(x) if x.dtype != np.float64 else len(x) - zb.size - rb.size  # not the inputs
        np.testing.assert_array_equal(x[:n], y[:n])
