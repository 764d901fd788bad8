"""The tracker's compiled step on preallocated arrays: predict, gate, assign, update,
confirm/delete, birth, and the snapshot of the confirmed tracks, in one call.

Each track is an IMM of a near-static and a constant-velocity model (imm.py): ``x``, ``P`` hold
its combined estimate (gated, assigned, reported), the model states and weights sit beside
them; with the IMM off it is the constant-velocity filter alone (kalman.py).

Track slots are rows of fixed arrays (the cap is their length); ``meta`` holds per slot the
status (0 free, 1 tentative, 2 confirmed), id, age, hits and misses. Confirmed tracks are
matched first, tentative ones get the targets left over, and targets nobody took start
tentative tracks (not inside a confirmed track's gate, where they are more likely a split
detection of that track than a new object). Nothing is allocated per acquisition: state,
scratch and the snapshot of the confirmed tracks (which the Tracker copies for its Track
objects) live in the arrays of :func:`spiel_edge.track.layout.allocate`. The reference for
every result is tests/track/reference_step.py (the step before this one).
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.track.assign import INFEASIBLE, assign_into
from spiel_edge.track.imm import combine_kernel, imm_update, mix_predict_kernel
from spiel_edge.track.kalman import gate_at, predict_kernel, sym_inv3, update_kernel
from spiel_edge.track.layout import (
    AGE,
    CONFIRMED,
    DROPPED,
    FREE,
    HITS,
    ID,
    META,
    MISSES,
    NEXT_ID,
    SLOTS,
    STATUS,
    TENTATIVE,
    measurement_buffers,
    scratch_views,
    snapshot_buffer,
    unpack,
)


@jit
def _measurement_noise(r: np.ndarray, out: np.ndarray, floor2: float, fallback2: float) -> None:
    """Symmetrised covariance plus the floor into ``out``; the fallback when it is not
    finite or not positive definite."""
    ok = True
    for i in range(3):
        for j in range(3):
            v = 0.5 * (r[i, j] + r[j, i])
            ok = ok and np.isfinite(v)
            out[i, j] = v
    if ok:
        for i in range(3):
            out[i, i] += floor2
        det = sym_inv3(out[0, 0], out[0, 1], out[0, 2], out[1, 1], out[1, 2], out[2, 2])[0]
        minor = out[0, 0] * out[1, 1] - out[0, 1] * out[1, 0]
        ok = out[0, 0] > 0.0 and minor > 0.0 and det > 0.0 and np.isfinite(det)
    if not ok:
        out[:, :] = 0.0
        for i in range(3):
            out[i, i] = fallback2 + floor2


@jit
def _finite_slot(x: np.ndarray, p: np.ndarray) -> bool:
    total = 0.0
    for i in range(6):
        total += x[i] * 0.0  # NaN or inf make it NaN
        for j in range(6):
            total += p[i, j] * 0.0
    return total == 0.0


@jit
def _match(x, p, meta, kind, z, r, usable, gated, gate, views) -> int:
    """Global assignment of the slots of status ``kind`` to the usable targets: fills
    ``slots`` and per slot ``chosen`` (a target or -1); returns how many slots."""
    cost, slots, chosen, fwork, owner, way, cols, used = views
    n = int(0)  # noqa: UP018 (an int64, not Literal[int]: one compiled signature)
    for s in range(meta.shape[1]):
        if meta[STATUS, s] == kind:
            slots[n] = s
            n += 1
    m = len(z)
    for a in range(n):
        s = slots[a]
        for j in range(m):
            cost[a, j] = INFEASIBLE
            if usable[j]:
                d2, det = gate_at(x, p, s, z, r, j, gate)
                if d2 <= gate:
                    cost[a, j] = d2 + np.log(det)
                    gated[j] = True
    assign_into(cost, n, m, chosen, fwork, owner, way, cols, used)
    return n


@jit
def step_kernel(floats, ints, bools, z, r_in, dt):
    """One acquisition on :func:`allocate`'s arrays. The parameters: acceleration, gate,
    floor^2, fallback^2, v0^2, confirm_hits, confirm_window, max_misses, and the IMM's
    static_q2 (mm^2/s), switch probability and static share at birth (imm.py; both of the
    last two 0: the constant-velocity filter alone, as before the IMM). Leaves per target the
    id of the confirmed track it went to, or -1, for :func:`target_ids`; returns the snapshot
    of the confirmed tracks (:func:`_snapshot`)."""
    n = _step_on(floats, ints, bools, z, r_in, dt)
    return snapshot_buffer(floats)[:n].copy()


# _nrt=False: the step allocates nothing (its snapshot goes to the float array too), and
# without numba's runtime its many views of the state skip their atomic reference counts
@jit(_nrt=False)
def step_buffered(floats, ints, bools, m, dt):
    """:func:`step_kernel` on the first ``m`` targets written into :func:`measurement_views`
    beforehand (two array arguments fewer: each costs time in the call); returns the number
    of confirmed tracks, whose snapshot :func:`snapshot_rows` copies out."""
    z, r_in = measurement_buffers(floats)
    return _step_on(floats, ints, bools, z[:m], r_in[:m], dt)


@jit(inline="always")
def _step_on(floats, ints, bools, z, r_in, dt):
    x, p, models, params, wf, meta, counters, wi, wb = unpack(floats, ints, bools)
    gate, floor2, fallback2 = params[1], params[2], params[3]
    confirm_hits, confirm_window, max_misses = int(params[5]), int(params[6]), int(params[7])
    imm = _imm_on(params)
    cap, m = meta.shape[1], len(z)
    r, work, mixing, target_slot, usable, near, scratch, match_views = scratch_views(wf, wi, wb, m)
    for j in range(m):
        _measurement_noise(r_in[j], r[j], floor2, fallback2)
        usable[j] = np.isfinite(z[j, 0]) and np.isfinite(z[j, 1]) and np.isfinite(z[j, 2])
        target_slot[j] = -1
        near[j] = False
        scratch[j] = False
    for s in range(cap):
        if meta[STATUS, s] != FREE:
            _predict_slot(x, p, models, mixing, s, dt, params, imm)
            meta[AGE, s] += 1
            meta[MISSES, s] += 1  # undone on a hit
    slots, chosen = match_views[1], match_views[2]
    for kind in (CONFIRMED, TENTATIVE):
        gated = near if kind == CONFIRMED else scratch
        n = _match(x, p, meta, kind, z, r, usable, gated, gate, match_views)
        for a in range(n):
            j, s = chosen[a], slots[a]
            if j >= 0 and _update_slot(x, p, models, s, z[j], r[j], work, imm):
                meta[HITS, s] += 1
                meta[MISSES, s] = 0
                target_slot[j] = s
                usable[j] = False
    _confirm_or_delete(x, p, meta, counters, confirm_hits, confirm_window, max_misses)
    _births(x, p, meta, counters, z, r, usable, near, target_slot, params[4], confirm_hits)
    if imm:  # a new track starts both models on its target
        for j in range(m):
            s = target_slot[j]
            if s >= 0 and meta[HITS, s] == 1 and meta[AGE, s] == 1:
                _start_models(x, p, models, s, params[10])
    for j in range(m):  # target_slot becomes per target the confirmed track's id or -1
        s = target_slot[j]
        target_slot[j] = meta[ID, s] if s >= 0 and meta[STATUS, s] == CONFIRMED else -1
    return _snapshot(x, p, meta, wi, snapshot_buffer(floats))


@jit(inline="always")
def _imm_on(params) -> bool:
    """The static model is in use: a switch probability or a static share at birth."""
    return params[9] > 0.0 or params[10] > 0.0


@jit(inline="always")
def _predict_slot(x, p, models, mixing, s, dt, params, imm):
    if imm:
        xm, pm, mu = models
        mix_x, mix_p = mixing
        mix_predict_kernel(
            xm[s], pm[s], mu[s], x[s], p[s], dt, params[0], params[8], params[9], params[4],
            mix_x, mix_p,
        )  # fmt: skip
    else:
        predict_kernel(x[s], p[s], dt, params[0])


@jit(inline="always")
def _update_slot(x, p, models, s, z, r, work, imm) -> bool:
    if imm:
        xm, pm, mu = models
        return imm_update(xm[s], pm[s], mu[s], x[s], p[s], z, r, work)
    return update_kernel(x[s], p[s], z, r, work)


@jit
def _start_models(x, p, models, s, static_share):
    xm, pm, mu = models
    for k in range(2):  # element loops: a slice copy may allocate (the step runs without NRT)
        for a in range(6):
            xm[s, k, a] = x[s, a]
            for b in range(6):
                pm[s, k, a, b] = p[s, a, b]
    mu[s, 0], mu[s, 1] = static_share, 1.0 - static_share
    combine_kernel(xm[s], pm[s], mu[s], x[s], p[s])


@jit
def _confirm_or_delete(x, p, meta, counters, confirm_hits, confirm_window, max_misses):
    for s in range(meta.shape[1]):
        status = meta[STATUS, s]
        if status == FREE:  # nothing to confirm or delete
            continue
        finite = _finite_slot(x[s], p[s])
        if status == TENTATIVE and finite and meta[HITS, s] >= confirm_hits:
            _confirm(meta, counters, s)
            continue
        if status == TENTATIVE:
            expired = meta[AGE, s] >= confirm_window
        else:
            expired = meta[MISSES, s] >= max_misses
        if status != FREE and (expired or not finite):
            meta[STATUS, s] = FREE


@jit
def _confirm(meta, counters, s):
    meta[STATUS, s] = CONFIRMED
    meta[ID, s] = counters[NEXT_ID]
    counters[NEXT_ID] += 1


@jit
def _births(x, p, meta, counters, z, r, usable, near, target_slot, v02, confirm_hits):
    """A tentative track (the first free slot) per target nobody took, outside confirmed
    tracks' gates; births beyond the cap are counted."""
    cap = meta.shape[1]
    for j in range(len(z)):
        if not usable[j] or near[j]:
            continue
        s = 0
        while s < cap and meta[STATUS, s] != FREE:
            s += 1
        if s == cap:
            counters[DROPPED] += 1
            continue
        x[s, 3:] = 0.0
        p[s] = 0.0
        for a in range(3):  # element loops: a slice copy may allocate (no NRT in the step)
            x[s, a] = z[j, a]
            for b in range(3):
                p[s, a, b] = r[j, a, b]
        for a in range(3, 6):
            p[s, a, a] = v02
        meta[STATUS, s], meta[ID, s], meta[AGE, s], meta[HITS, s], meta[MISSES, s] = (
            TENTATIVE,
            -1,
            1,
            1,
            0,
        )
        if confirm_hits <= 1:
            _confirm(meta, counters, s)
        target_slot[j] = s


@jit
def _snapshot(x, p, meta, wi, out):
    """The confirmed tracks by id into the rows of ``out``: state (6) and covariance (36,
    row-major); their id, age, hits and misses go to ``snapshot_meta(wi, rows)``. Returns the
    number of rows."""
    order = wi[:SLOTS]
    n = 0
    for s in range(meta.shape[1]):
        if meta[STATUS, s] == CONFIRMED:  # insertion sort by id (ids are unique)
            k = n
            while k > 0 and meta[ID, order[k - 1]] > meta[ID, s]:
                order[k] = order[k - 1]
                k -= 1
            order[k] = s
            n += 1
    for k in range(n):
        s = order[k]
        for c in range(4):
            wi[META + 4 * k + c] = meta[ID + c, s]
        for i in range(6):
            out[k, i] = x[s, i]
        for i in range(6):
            for j in range(6):
                out[k, 6 + 6 * i + j] = p[s, i, j]
    return n


@jit
def snapshot_now(floats, ints, bools):
    """:func:`_snapshot` outside a step (``Tracker.tracks``): the number of rows."""
    x, p, _, _, _, meta, _, wi, _ = unpack(floats, ints, bools)
    return _snapshot(x, p, meta, wi, snapshot_buffer(floats))
