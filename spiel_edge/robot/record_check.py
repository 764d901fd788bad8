"""A board record from the network, checked field by field before anything uses it.

``fuse`` takes records from other processes and other computers: a broken or hostile peer
must cost only its own messages. Every bound is checked per message, and a message that
breaks one is refused whole (:class:`Refused`, with a short reason the summary counts): not
JSON, larger than MAX_RECORD_BYTES, nested deeper than MAX_DEPTH, more than MAX_TARGETS
targets, a NaN or infinite number, a position or score out of range, a covariance that is
not symmetric positive definite, a stamp that is not a time. Nothing here raises anything
but :class:`Refused`.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np

MAX_RECORD_BYTES = 1 << 20  # a board record is a few kB
MAX_DEPTH = 32  # a record nests 4 deep; Python's parser would recurse 100,000 deep
MAX_TARGETS = 64  # a board reports at most 16 (--max-targets); the fuser pairs them (n^2)
MAX_POSITION_MM = 1e5  # 100 m: no echo comes from further
MAX_VARIANCE_MM2 = 1e10  # (100 m)^2
MIN_EIGENVALUE_MM2 = 1e-6  # positive definite, and well enough to invert
MAX_SCORE = 1e6
MAX_DEVICE_US = 1 << 53  # exact in a double: 285 years of microseconds
MAX_CROSSTALK = 16  # board names (MAX_BOARDS)
MAX_NAME = 64
MAX_REASON = 200
DEFAULT_COVARIANCE_MM2 = 400.0  # a target without one: 20 mm each way

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)


class Refused(ValueError):
    """A message that is not a usable board record; ``reason``: a few words to count by."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


def json_depth(payload: bytes, limit: int = MAX_DEPTH) -> int:
    """How deep ``[``/``{`` nest in ``payload`` (outside strings), without parsing it; the
    count stops once past ``limit``."""
    if payload.count(b"[") + payload.count(b"{") <= limit:
        return 0  # cannot nest deeper than it opens: the common case, in microseconds
    depth = deepest = 0
    for c in _STRING.sub(b"", payload).translate(None, _NOT_BRACKETS):
        depth += 1 if c in (0x5B, 0x7B) else -1
        if depth > deepest:
            deepest = depth
            if deepest > limit:
                break
    return deepest


def parse(payload: bytes) -> dict:
    """The record ``payload`` holds (a JSON object), or Refused."""
    if len(payload) > MAX_RECORD_BYTES:
        raise Refused("too large", f"{len(payload)} bytes")
    if json_depth(payload) > MAX_DEPTH:
        raise Refused("too deep", f"JSON nested deeper than {MAX_DEPTH}")
    try:
        record = json.loads(payload, parse_constant=_no_constant)
    except Refused:
        raise
    except (ValueError, RecursionError, MemoryError) as exc:
        raise Refused("not JSON", type(exc).__name__) from None
    if not isinstance(record, dict):
        raise Refused("not a record", "not a JSON object")
    return record


def _no_constant(name: str):
    raise Refused("not finite", f"{name} in the JSON")


def _finite(value, what: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Refused("not a record", f"{what} is not a number")
    v = float(value)
    if not math.isfinite(v):
        raise Refused("not finite", what)
    if not lo <= v <= hi:
        raise Refused("out of range", what)
    return v


def fields(record: dict) -> dict:
    """What the fuser takes from a board's record (``run``'s JSON), every field checked."""
    if "device_time_us" not in record or "host_time" not in record:
        raise Refused("not a record", "no device_time_us or host_time")
    device_us = _finite(record["device_time_us"], "device_time_us", 0, MAX_DEVICE_US)
    remote = _finite(record["host_time"], "host_time", -1e12, 1e12)
    acquisition = record.get("acquisition", -1)
    if isinstance(acquisition, bool) or not isinstance(acquisition, int):
        raise Refused("not a record", "acquisition is not an integer")
    if not -1 <= acquisition <= MAX_DEVICE_US:
        raise Refused("out of range", "acquisition")
    crosstalk = record.get("crosstalk") or []
    if not (
        isinstance(crosstalk, list)
        and len(crosstalk) <= MAX_CROSSTALK
        and all(isinstance(b, str) and len(b) <= MAX_NAME for b in crosstalk)
    ):
        raise Refused("not a record", "crosstalk is not a short list of board names")
    synced = record.get("stamp_host")
    synced = 0.0 if synced is None else _finite(synced, "stamp_host", -1e12, 1e12)
    reason = record.get("reason")
    return {
        "stamp": device_us / 1e6,
        "remote": remote,
        "synced": synced,
        "acquisition": acquisition,
        "device_time_us": int(device_us),
        "targets": targets(record.get("targets")),
        "crosstalk": crosstalk,
        "error": str(reason)[:MAX_REASON] if record.get("error") else None,
    }


def targets(items) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """A record's targets as (position mm, covariance mm^2, score); Refused if any is bad."""
    if items is None:
        return []
    if not isinstance(items, list):
        raise Refused("not a record", "targets is not a list")
    if len(items) > MAX_TARGETS:
        raise Refused("too many targets", f"{len(items)} > {MAX_TARGETS}")
    out = []
    for k, t in enumerate(items):
        if not isinstance(t, dict):
            raise Refused("not a record", f"target {k} is not an object")
        p = np.array(_array(t.get("position_mm"), 3, f"target {k} position_mm", MAX_POSITION_MM))
        c = t.get("covariance_mm2")
        c = np.eye(3) * DEFAULT_COVARIANCE_MM2 if c is None else _covariance(c, k)
        out.append((p, c, _finite(t.get("score", 0.0), f"target {k} score", -MAX_SCORE, MAX_SCORE)))
    return out


def _array(value, n: int, what: str, bound: float = 1e300) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        raise Refused("not a record", f"{what} is not {n} numbers")
    return [_finite(v, what, -bound, bound) for v in value]


def _covariance(value, k: int) -> np.ndarray:
    """Symmetric, and positive definite: every pivot of its Cholesky factorisation above
    MIN_EIGENVALUE_MM2 (plain floats: a few microseconds, where numpy costs tens)."""
    what = f"target {k} covariance_mm2"
    if not isinstance(value, list) or len(value) != 3:
        raise Refused("not a record", f"{what} is not 3 x 3")
    try:
        c = [_array(row, 3, what, MAX_VARIANCE_MM2) for row in value]
    except Refused as exc:
        raise Refused(
            "out of range" if exc.reason == "out of range" else exc.reason, what
        ) from None
    scale = max(1.0, max(abs(v) for row in c for v in row))
    if any(abs(c[i][j] - c[j][i]) > 1e-6 * scale for i, j in ((0, 1), (0, 2), (1, 2))):
        raise Refused("bad covariance", f"{what} is not symmetric")
    a, b, d = c[0][0], c[0][1], c[0][2]
    e, f, g = c[1][1], c[1][2], c[2][2]
    p1 = a
    p2 = e - b * b / a if p1 > MIN_EIGENVALUE_MM2 else 0.0
    p3 = (g - d * d / a - (f - b * d / a) ** 2 / p2) if p2 > MIN_EIGENVALUE_MM2 else 0.0
    if not (p1 > MIN_EIGENVALUE_MM2 and p2 > MIN_EIGENVALUE_MM2 and p3 > MIN_EIGENVALUE_MM2):
        raise Refused("bad covariance", f"{what} is not positive definite")
    return np.array(c)  # symmetric within 1e-6: to_base symmetrises it exactly
