"""The tracker's arrays: their layout and views (the step itself is in step.py).

A tracker holds three arrays from :func:`allocate`: floats (each slot's state and covariance,
the IMM's model states and probabilities, the parameters, then the step's scratch: gating
costs, measurement noise, work space, the snapshot of the confirmed tracks and, last, the
targets written in by the Tracker), ints (each slot's status, id, age, hits, misses; the
counters; integer scratch) and bools (scratch). At most SLOTS tracks and SLOTS targets.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit

FREE, TENTATIVE, CONFIRMED = 0, 1, 2
STATUS, ID, AGE, HITS, MISSES = 0, 1, 2, 3, 4  # rows of ``meta``
NEXT_ID, DROPPED, CAP = 0, 1, 2  # entries of ``counters``


def allocate(cap: int, params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracker's float, int and bool arrays for ``cap`` (<= SLOTS) tracks: the state,
    the parameters (see :func:`_step`), every scratch the step needs and its snapshot, so
    that the step allocates nothing and takes few arguments (each one costs time)."""
    if not 1 <= cap <= SLOTS:
        raise ValueError(f"cap must be 1..{SLOTS}, got {cap}")
    if len(params) != N_PARAMS:
        raise ValueError(f"params must have {N_PARAMS} entries, got {len(params)}")
    floats = np.zeros(_F_SCRATCH + _FLOATS)
    floats[_F_PARAMS:_F_SCRATCH] = params
    ints = np.zeros(_I_SCRATCH + _INTS, np.int64)
    ints[_I_META + ID * SLOTS : _I_META + (ID + 1) * SLOTS] = -1
    ints[_I_COUNTS + CAP] = cap
    return floats, ints, np.zeros(_BOOLS, np.bool_)


def state_views(floats: np.ndarray, ints: np.ndarray):
    """(x (cap, 6), P (cap, 6, 6), meta (5, cap), counters (3,)): views of :func:`allocate`'s
    arrays."""
    cap = int(ints[_I_COUNTS + CAP])
    x = floats[: SLOTS * 6].reshape(SLOTS, 6)[:cap]
    p = floats[SLOTS * 6 : _F_MODELS].reshape(SLOTS, 6, 6)[:cap]
    meta = ints[_I_META:_I_COUNTS].reshape(5, SLOTS)[:, :cap]
    return x, p, meta, ints[_I_COUNTS:_I_SCRATCH]


def model_views(floats: np.ndarray, cap: int):
    """(xm (cap, 2, 6), pm (cap, 2, 6, 6), mu (cap, 2)): the IMM's model states (imm.py),
    meaningful while the IMM is on (``step._imm_on``)."""
    xm = floats[_F_MODELS : _F_MODELS + SLOTS * 12].reshape(SLOTS, 2, 6)[:cap]
    pm = floats[_F_MODELS + SLOTS * 12 : _F_MU].reshape(SLOTS, 2, 6, 6)[:cap]
    return xm, pm, floats[_F_MU:_F_PARAMS].reshape(SLOTS, 2)[:cap]


SNAPSHOT = 6 + 36  # columns of a snapshot row
N_PARAMS = 11  # see Tracker: the CV filter's 8, then static_q2, switch, static share at birth

# the scratch layout: at most SLOTS tracks and SLOTS targets, N = SLOTS + 1 for the Hungarian
SLOTS = 64
_N = SLOTS + 1
_COST, _R, _WORK, _MIX = SLOTS * SLOTS, SLOTS * 9, 6 * 15, 2 * 42
_SNAP = _COST + _R + _WORK + 3 * _N + _MIX  # the snapshot's rows
_Z = _SNAP + SLOTS * SNAPSHOT  # the targets' positions and covariances (last)
_FLOATS = _Z + SLOTS * 12
_META = 3 * SLOTS + 3 * _N  # the snapshot's ids, ages, hits, misses
_INTS = _META + 4 * SLOTS
_BOOLS = 3 * SLOTS + _N
# the state before the scratch: x, P (the track's estimate), the IMM's model states and
# probabilities, the parameters; meta, the counters
_F_MODELS = SLOTS * 42
_F_MU = _F_MODELS + SLOTS * 84
_F_PARAMS = _F_MU + SLOTS * 2
_F_SCRATCH = _F_PARAMS + N_PARAMS
_I_META, _I_COUNTS, _I_SCRATCH = 0, 5 * SLOTS, 5 * SLOTS + 3


@jit(inline="always")
def _unpack(floats, ints, bools):
    cap = ints[_I_COUNTS + CAP]
    x = floats[: SLOTS * 6].reshape((SLOTS, 6))[:cap]
    p = floats[SLOTS * 6 : _F_MODELS].reshape((SLOTS, 6, 6))[:cap]
    xm = floats[_F_MODELS : _F_MODELS + SLOTS * 12].reshape((SLOTS, 2, 6))[:cap]
    pm = floats[_F_MODELS + SLOTS * 12 : _F_MU].reshape((SLOTS, 2, 6, 6))[:cap]
    mu = floats[_F_MU:_F_PARAMS].reshape((SLOTS, 2))[:cap]
    params = floats[_F_PARAMS:_F_SCRATCH]
    meta = ints[_I_META:_I_COUNTS].reshape((5, SLOTS))[:, :cap]
    counters = ints[_I_COUNTS:_I_SCRATCH]
    models = (xm, pm, mu)
    return x, p, models, params, floats[_F_SCRATCH:], meta, counters, ints[_I_SCRATCH:], bools


@jit(inline="always")
def _views(wf, wi, wb, m):
    r = wf[_COST : _COST + _R].reshape((SLOTS, 3, 3))[:m]
    at = _COST + _R
    work = wf[at : at + _WORK].reshape((6, 15))
    at += _WORK
    fwork = wf[at : at + 3 * _N].reshape((3, _N))
    at += 3 * _N
    mixing = (wf[at : at + 12].reshape((2, 6)), wf[at + 12 : at + _MIX].reshape((2, 6, 6)))
    cost = wf[:_COST].reshape((SLOTS, SLOTS))
    slots, chosen, target_slot = wi[:SLOTS], wi[SLOTS : 2 * SLOTS], wi[2 * SLOTS : 3 * SLOTS]
    owner, way, cols = (
        wi[3 * SLOTS : 3 * SLOTS + _N],
        wi[3 * SLOTS + _N : 3 * SLOTS + 2 * _N],
        wi[3 * SLOTS + 2 * _N :],
    )
    usable, near, scratch = wb[:SLOTS], wb[SLOTS : 2 * SLOTS], wb[2 * SLOTS : 3 * SLOTS]
    used = wb[3 * SLOTS :]
    views = (cost, slots, chosen, fwork, owner, way, cols, used)
    return r, work, mixing, target_slot, usable, near, scratch, views


@jit(inline="always")
def _measurement_buffers(floats):
    at = _F_SCRATCH + _Z
    z = floats[at : at + SLOTS * 3].reshape((SLOTS, 3))
    return z, floats[at + SLOTS * 3 : at + SLOTS * 12].reshape((SLOTS, 3, 3))


@jit(inline="always")
def _snapshot_buffer(floats):
    at = _F_SCRATCH + _SNAP
    return floats[at : at + SLOTS * SNAPSHOT].reshape((SLOTS, SNAPSHOT))


def snapshot_rows(floats: np.ndarray, rows: int) -> np.ndarray:
    """A copy of the snapshot's first ``rows`` rows (after :func:`_step_buffered` or
    :func:`_snapshot_now`): the Track objects keep it while the buffer is reused."""
    at = _F_SCRATCH + _SNAP
    return floats[at : at + rows * SNAPSHOT].reshape(rows, SNAPSHOT).copy()


def measurement_views(floats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z (SLOTS, 3), r (SLOTS, 3, 3)): views of :func:`allocate`'s float array where
    :func:`_step_buffered` reads the targets' positions and covariances."""
    at = _F_SCRATCH + _Z
    z = floats[at : at + SLOTS * 3].reshape(SLOTS, 3)
    return z, floats[at + SLOTS * 3 : at + SLOTS * 12].reshape(SLOTS, 3, 3)


def target_ids(ints: np.ndarray, m: int) -> list[int]:
    """After :func:`_step` with ``m`` targets: per target its confirmed track's id or -1."""
    at = _I_SCRATCH + 2 * SLOTS
    return ints[at : at + m].tolist()


def snapshot_meta(ints: np.ndarray, rows: int) -> list[int]:
    """After :func:`_snapshot` of ``rows`` tracks: id, age, hits, misses of each, flat."""
    at = _I_SCRATCH + _META
    return ints[at : at + 4 * rows].tolist()
