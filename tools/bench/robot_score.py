"""Scoring the virtual robot (tools/bench/robot_eval.py, tests/robot/): pure functions over fused
records and the world's truth.

- *Crossings*: a mover's primary board (the one that sees it nearest its facing, among those
  with the mover within ``VIEW_DEG`` of their facing) changes and the new one stays primary for
  ``HOLD`` cycles; see :func:`crossing_ids` for how each is counted.
- *Coverage*: per cycle, confirmed tracks matched one-to-one to movers within ``GATE_MM``
  (nearest pairs first); the tracked error is the matched distance.
- *The association's share* (:func:`oracle_records`): the same fused targets, associated to the
  movers by the truth instead of by the tracker, one track per mover with the same filter
  and coasting; scored the same way, it bounds what a better association could win.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.fusion import BaseTarget
from spiel_edge.track import Tracker

GATE_MM = 40.0
VIEW_DEG = 50.0
HOLD = 4
LOOK = 12
ORACLE_GATE_MM = 80.0  # a fused target this near its mover (and nearest to it) is the mover's


def match(
    points: np.ndarray, truths: np.ndarray, gate: float = GATE_MM
) -> dict[int, tuple[int, float]]:
    """One-to-one, nearest pairs first: {truth index: (point index, distance)}."""
    if not len(points) or not len(truths):
        return {}
    d = np.linalg.norm(np.asarray(points)[:, None, :] - np.asarray(truths)[None, :, :], axis=2)
    out: dict[int, tuple[int, float]] = {}
    used: set[int] = set()
    for flat in np.argsort(d, axis=None):
        i, j = divmod(int(flat), d.shape[1])
        if d[i, j] > gate:
            break
        if i in used or j in out:
            continue
        used.add(i)
        out[j] = (i, float(d[i, j]))
    return out


def coverage(
    records: list[dict], truths: list[np.ndarray]
) -> tuple[list[dict[int, int]], list[float]]:
    """Per cycle {mover: track id} of the covering tracks, and every matched distance."""
    ids, errors = [], []
    for rec, truth in zip(records, truths, strict=True):
        tracks = rec.get("tracks") or []
        pos = np.array([t["position_mm"] for t in tracks]).reshape(-1, 3)
        m = match(pos, truth)
        ids.append({j: int(tracks[i]["track_id"]) for j, (i, _) in m.items()})
        errors += [d for _, d in m.values()]
    return ids, errors


def paired_errors(
    records: list[dict], truths: list[np.ndarray], primary: np.ndarray, names, own: dict
) -> dict:
    """Like for like: per cycle and mover whose primary board's acquisition in that cycle has
    its own tracker's error for it (``own[(board, acquisition)][mover]``) and a fused track
    matched to it, both errors (the same movers, the same cycles); their means and medians."""
    fused, single = [], []
    for k, (rec, truth) in enumerate(zip(records, truths, strict=True)):
        tracks = rec.get("tracks") or []
        pos = np.array([t["position_mm"] for t in tracks]).reshape(-1, 3)
        for j, (_, d) in match(pos, truth).items():
            b = primary[k, j]
            acq = rec["boards"].get(names[b], {}).get("acquisition") if b >= 0 else None
            e = own.get((names[b], acq), {}).get(j) if acq is not None else None
            if e is not None:
                fused.append(d)
                single.append(e)
    if not fused:
        return {"n": 0}
    f, s = np.asarray(fused), np.asarray(single)
    return {
        "n": len(f),
        "fused_mean": round(float(f.mean()), 2),
        "own_mean": round(float(s.mean()), 2),
        "fused_median": round(float(np.median(f)), 2),
        "own_median": round(float(np.median(s)), 2),
    }


def primary_boards(world, truths: list[np.ndarray]) -> np.ndarray:
    """(cycles, movers) index of the board seeing each mover nearest its facing, -1: none."""
    names = world.names
    out = np.full((len(truths), len(truths[0]) if truths else 0), -1)
    cos_view = np.cos(np.radians(VIEW_DEG))
    for c, truth in enumerate(truths):
        best = np.full(len(truth), cos_view)
        for b, name in enumerate(names):
            v = truth - world.emitters[name]
            cos = v @ world.facing[name] / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
            better = cos > best
            out[c, better] = b
            best = np.maximum(best, cos)
    return out


def crossings(primary: np.ndarray) -> list[tuple[int, int]]:
    """(cycle, mover) of every crossing (see the module docstring)."""
    out = []
    for j in range(primary.shape[1]):
        col = primary[:, j]
        current, since = -1, 0
        for c in range(len(col)):
            b = col[c]
            if b < 0 or b == current:
                continue
            hold = col[c : c + HOLD]
            if len(hold) == HOLD and np.all(hold == b):
                if current >= 0:
                    out.append((c, j))
                current, since = b, c
    del since
    return out


def crossing_ids(
    ids: list[dict[int, int]],
    events: list[tuple[int, int]],
    reported: list[set[int]] | None = None,
    truths: list[np.ndarray] | None = None,
) -> dict[str, int]:
    """Per crossing: ``untracked`` (no track covered the mover in the ``LOOK`` cycles before
    it: no id to keep), else ``kept`` (the first track covering it in the ``LOOK`` cycles
    after is the same), ``changed`` (another track) or ``lost`` (none). With ``reported``
    (per cycle the movers some board reported a target within ``GATE_MM`` of, before any
    fusion), ``unreported_after`` counts the changed or lost ones no board reported in the
    ``LOOK`` cycles after: no measurement there to keep the id with. With ``truths``,
    ``near_another`` counts (first) the changed or lost ones with another mover within
    2 ``GATE_MM`` of it in the ``LOOK`` cycles either side (two movers one target, or tracks
    that the one-to-one matching may swap).
    """
    out = {"crossings": len(events), "untracked": 0, "kept": 0, "changed": 0, "lost": 0}
    if reported is not None:
        out["unreported_after"] = 0
    if truths is not None:
        out["near_another"] = 0
    for c, j in events:
        before, after = crossing_outcome(ids, c, j)
        if before is None:
            out["untracked"] += 1
        elif after is None:
            out["lost"] += 1
        else:
            out["kept" if before == after else "changed"] += 1
        if before is None or before == after:
            continue
        if truths is not None and any(
            np.sort(np.linalg.norm(truths[k] - truths[k][j], axis=1))[1] < 2 * GATE_MM
            for k in range(max(c - LOOK, 0), min(c + LOOK, len(truths)))
        ):
            out["near_another"] += 1
        elif reported is not None and not any(
            j in reported[k] for k in range(c, min(c + LOOK, len(reported)))
        ):
            out["unreported_after"] += 1
    return out


def crossing_outcome(ids: list[dict[int, int]], c: int, j: int) -> tuple[int | None, int | None]:
    """Mover ``j``'s crossing at cycle ``c``: the id of the last track covering it in the
    ``LOOK`` cycles before and of the first in the ``LOOK`` cycles after (None: none)."""
    before = next((ids[k][j] for k in range(c - 1, max(c - 1 - LOOK, -1), -1) if j in ids[k]), None)
    after = next((ids[k][j] for k in range(c, min(c + LOOK, len(ids))) if j in ids[k]), None)
    return before, after


def oracle_records(
    records: list[dict],
    truths: list[np.ndarray],
    make_tracker: Callable[[], Tracker],
    make_coast: Callable[[], CoastPolicy | None] = lambda: None,
    gate: float = ORACLE_GATE_MM,
) -> list[dict]:
    """Records whose ``tracks`` come from one tracker per mover, fed the cycle's fused target
    nearest that mover when the mover is also the target's nearest and within ``gate`` (the
    truth's association, no confusion between movers), with the same coasting (ids: mover
    ``j``'s track ``i`` is ``1000 j + i``)."""
    n = len(truths[0]) if truths else 0
    trackers = [make_tracker() for _ in range(n)]
    coasts = [make_coast() for _ in range(n)]
    out = []
    for rec, truth in zip(records, truths, strict=True):
        t = float(rec["host_time"])
        targets = rec.get("targets") or []
        pos = np.array([x["position_mm"] for x in targets], float).reshape(-1, 3)
        d = np.linalg.norm(pos[:, None, :] - truth[None, :, :], axis=2)  # (targets, movers)
        owner = np.argmin(d, axis=1) if len(pos) else np.zeros(0, int)
        tracks = []
        for j in range(n):
            mine = np.flatnonzero((owner == j) & (d[:, j] < gate)) if len(pos) else []
            given = []
            if len(mine):
                i = int(mine[np.argmin(d[mine, j])])
                cov = np.asarray(targets[i]["covariance_mm2"], float)
                given = [BaseTarget(pos[i], cov, list(targets[i].get("boards", [])))]
            if coasts[j] is not None:
                coasts[j].hold(trackers[j], t)
            for tr in trackers[j].update(given, t):
                tracks.append(
                    {
                        "track_id": 1000 * j + int(tr.track_id),
                        "position_mm": tr.position_mm.tolist(),
                    }
                )
        out.append({"tracks": tracks})
    return out
