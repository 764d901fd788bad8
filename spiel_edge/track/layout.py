"""The tracker's arrays: their layout and views (the step itself is in step.py).

A tracker holds three arrays from :func:`allocate`: floats (each slot's state and covariance,
the IMM's model states and probabilities, the parameters, then the step's scratch: gating
costs, measurement noise, work space, the snapshot of the confirmed tracks and, last, the
targets written in by the Tracker), ints (each slot's status, id, age, hits, misses; the
counters; integer scratch) and bools (scratch). At most SLOTS tracks and SLOTS targets.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._abi import Field, Table
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
    x = floats[:_F_P].reshape(SLOTS, 6)[:cap]
    p = floats[_F_P:_F_MODELS].reshape(SLOTS, 6, 6)[:cap]
    meta = ints[_I_META:_I_COUNTS].reshape(5, SLOTS)[:, :cap]
    return x, p, meta, ints[_I_COUNTS:_I_SCRATCH]


def model_views(floats: np.ndarray, cap: int):
    """(xm (cap, 2, 6), pm (cap, 2, 6, 6), mu (cap, 2)): the IMM's model states (imm.py),
    meaningful while the IMM is on (``step._imm_on``)."""
    xm = floats[_F_MODELS:_F_PM].reshape(SLOTS, 2, 6)[:cap]
    pm = floats[_F_PM:_F_MU].reshape(SLOTS, 2, 6, 6)[:cap]
    return xm, pm, floats[_F_MU:_F_PARAMS].reshape(SLOTS, 2)[:cap]


SNAPSHOT = 6 + 36  # columns of a snapshot row
N_PARAMS = 11  # see Tracker: the CV filter's 8, then static_q2, switch, static share at birth
SLOTS = 64  # at most SLOTS tracks and SLOTS targets
_N = SLOTS + 1  # the Hungarian's size

_F, _I, _B = np.float64, np.int64, np.bool_
# the state, first in each array (the scheme of spiel_edge._abi, as the compiled pipeline's)
STATE = Table(
    (
        Field("x", _F, (SLOTS, 6)),  # each slot's estimate
        Field("p", _F, (SLOTS, 6, 6)),
        Field("xm", _F, (SLOTS, 2, 6)),  # the IMM's model states and probabilities
        Field("pm", _F, (SLOTS, 2, 6, 6)),
        Field("mu", _F, (SLOTS, 2)),
        Field("params", _F, (N_PARAMS,)),
        Field("meta", _I, (5, SLOTS)),  # status, id, age, hits, misses
        Field("counters", _I, (3,)),
    ),
    (_F, _I, _B),
)
# the step's scratch, after the state
SCRATCH = Table(
    (
        Field("cost", _F, (SLOTS, SLOTS)),  # gating costs
        Field("r", _F, (SLOTS, 3, 3)),  # measurement noise
        Field("work", _F, (6, 15)),
        Field("fwork", _F, (3, _N)),
        Field("mix_x", _F, (2, 6)),  # the IMM's mixing
        Field("mix_p", _F, (2, 6, 6)),
        Field("snapshot", _F, (SLOTS, SNAPSHOT)),  # the confirmed tracks
        Field("z", _F, (SLOTS, 3)),  # the targets, written in by the Tracker (last)
        Field("zr", _F, (SLOTS, 3, 3)),
        Field("slots", _I, (SLOTS,)),
        Field("chosen", _I, (SLOTS,)),
        Field("target_slot", _I, (SLOTS,)),
        Field("owner", _I, (_N,)),
        Field("way", _I, (_N,)),
        Field("cols", _I, (_N,)),
        Field("snap_meta", _I, (4, SLOTS)),  # the snapshot's ids, ages, hits, misses
        Field("usable", _B, (SLOTS,)),
        Field("near", _B, (SLOTS,)),
        Field("scratch", _B, (SLOTS,)),
        Field("used", _B, (_N,)),
    ),
    (_F, _I, _B),
)
# where each part starts: in the whole arrays (_F_*, _I_*), in the scratch (the rest)
_F_P, _F_MODELS, _F_PM = STATE.offset("p"), STATE.offset("xm"), STATE.offset("pm")
_F_MU, _F_PARAMS = STATE.offset("mu"), STATE.offset("params")
_F_SCRATCH = STATE.total(_F)
_I_META, _I_COUNTS, _I_SCRATCH = STATE.offset("meta"), STATE.offset("counters"), STATE.total(_I)
_R, _WORK, _FWORK = SCRATCH.offset("r"), SCRATCH.offset("work"), SCRATCH.offset("fwork")
_MIX_X, _MIX_P = SCRATCH.offset("mix_x"), SCRATCH.offset("mix_p")
_SNAP, _Z, _ZR = SCRATCH.offset("snapshot"), SCRATCH.offset("z"), SCRATCH.offset("zr")
_CHOSEN, _TARGET_SLOT = SCRATCH.offset("chosen"), SCRATCH.offset("target_slot")
_OWNER, _WAY, _COLS = SCRATCH.offset("owner"), SCRATCH.offset("way"), SCRATCH.offset("cols")
META = SCRATCH.offset("snap_meta")
_NEAR, _SCRATCH, _USED = SCRATCH.offset("near"), SCRATCH.offset("scratch"), SCRATCH.offset("used")
_FLOATS, _INTS, _BOOLS = SCRATCH.total(_F), SCRATCH.total(_I), SCRATCH.total(_B)


@jit(inline="always")
def unpack(floats, ints, bools):
    cap = ints[_I_COUNTS + CAP]
    x = floats[:_F_P].reshape((SLOTS, 6))[:cap]
    p = floats[_F_P:_F_MODELS].reshape((SLOTS, 6, 6))[:cap]
    xm = floats[_F_MODELS:_F_PM].reshape((SLOTS, 2, 6))[:cap]
    pm = floats[_F_PM:_F_MU].reshape((SLOTS, 2, 6, 6))[:cap]
    mu = floats[_F_MU:_F_PARAMS].reshape((SLOTS, 2))[:cap]
    params = floats[_F_PARAMS:_F_SCRATCH]
    meta = ints[_I_META:_I_COUNTS].reshape((5, SLOTS))[:, :cap]
    counters = ints[_I_COUNTS:_I_SCRATCH]
    models = (xm, pm, mu)
    return x, p, models, params, floats[_F_SCRATCH:], meta, counters, ints[_I_SCRATCH:], bools


@jit(inline="always")
def scratch_views(wf, wi, wb, m):
    """The step's scratch (``wf``, ``wi``, ``wb``: the arrays from _F_SCRATCH, _I_SCRATCH, 0)
    as SCRATCH lays it out."""
    r = wf[_R:_WORK].reshape((SLOTS, 3, 3))[:m]
    work = wf[_WORK:_FWORK].reshape((6, 15))
    fwork = wf[_FWORK:_MIX_X].reshape((3, _N))
    mixing = (wf[_MIX_X:_MIX_P].reshape((2, 6)), wf[_MIX_P:_SNAP].reshape((2, 6, 6)))
    cost = wf[:_R].reshape((SLOTS, SLOTS))
    slots, chosen, target_slot = wi[:_CHOSEN], wi[_CHOSEN:_TARGET_SLOT], wi[_TARGET_SLOT:_OWNER]
    owner, way, cols = wi[_OWNER:_WAY], wi[_WAY:_COLS], wi[_COLS:]
    usable, near, scratch = wb[:_NEAR], wb[_NEAR:_SCRATCH], wb[_SCRATCH:_USED]
    used = wb[_USED:]
    views = (cost, slots, chosen, fwork, owner, way, cols, used)
    return r, work, mixing, target_slot, usable, near, scratch, views


@jit(inline="always")
def measurement_buffers(floats):
    z = floats[_F_SCRATCH + _Z : _F_SCRATCH + _ZR].reshape((SLOTS, 3))
    return z, floats[_F_SCRATCH + _ZR : _F_SCRATCH + _FLOATS].reshape((SLOTS, 3, 3))


@jit(inline="always")
def snapshot_buffer(floats):
    return floats[_F_SCRATCH + _SNAP : _F_SCRATCH + _Z].reshape((SLOTS, SNAPSHOT))


def snapshot_rows(floats: np.ndarray, rows: int) -> np.ndarray:
    """A copy of the snapshot's first ``rows`` rows (after :func:`step.step_buffered` or
    :func:`step.snapshot_now`): the Track objects keep it while the buffer is reused."""
    at = _F_SCRATCH + _SNAP
    return floats[at : at + rows * SNAPSHOT].reshape(rows, SNAPSHOT).copy()


def measurement_views(floats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(z (SLOTS, 3), r (SLOTS, 3, 3)): views of :func:`allocate`'s float array where
    :func:`step.step_buffered` reads the targets' positions and covariances."""
    z = floats[_F_SCRATCH + _Z : _F_SCRATCH + _ZR].reshape(SLOTS, 3)
    return z, floats[_F_SCRATCH + _ZR : _F_SCRATCH + _FLOATS].reshape(SLOTS, 3, 3)


def target_ids(ints: np.ndarray, m: int) -> list[int]:
    """After :func:`_step` with ``m`` targets: per target its confirmed track's id or -1."""
    at = _I_SCRATCH + _TARGET_SLOT
    return ints[at : at + m].tolist()


def snapshot_meta(ints: np.ndarray, rows: int) -> list[int]:
    """After :func:`_snapshot` of ``rows`` tracks: id, age, hits, misses of each, flat."""
    at = _I_SCRATCH + META
    return ints[at : at + 4 * rows].tolist()
