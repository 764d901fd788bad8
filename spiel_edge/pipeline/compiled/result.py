"""The Result of one acquisition from an acquisition kernel's outputs, as the staged path
builds it (``Pipeline._locate``): the only Python the compiled path runs per acquisition."""

from __future__ import annotations

from spiel_edge.pipeline.staged import REASON_SOLVE_FAILED, Result, Target
from spiel_edge.pipeline.stages.features import TOA_COLUMN


def match_list(row: list[int]) -> list[int | None]:
    return [m if m >= 0 else None for m in row]


def result(pipeline, features, counts, raw, targets: list[Target], first: list[int]) -> Result:
    """The Result with ``targets`` (best first), or without a target: its reason, with the
    first hypothesis's echoes (``first``, -1 for none) as ``matched``."""
    toa = features[:, :, TOA_COLUMN]  # tolist: Python floats and ints, as the staged lists
    echoes = [toa[c, :n].tolist() for c, n in enumerate(counts.tolist())]
    base = {"features": features, "counts": counts}
    if not targets:
        matched = match_list(first)
        used = sum(m is not None for m in matched)
        reason = REASON_SOLVE_FAILED if used >= 3 else pipeline.why_empty(raw, counts)
        return Result(None, reason, None, echoes, matched, **base)
    best = targets[0]
    return Result(
        best.position_mm, None, best.residual_mm, echoes, best.matched, targets=targets, **base
    )
