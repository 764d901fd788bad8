"""Figures of docs/security.md: what checking and authenticating a board record costs, and
how fast `fuse` refuses the issue's hostile messages. Prints one JSON document.

    .venv/bin/python tools/security_figures.py
"""

from __future__ import annotations

import json
import time

import numpy as np

from spiel_edge.robot import record_auth, record_check


def _per_call_us(fn, n: int) -> float:
    best = float("inf")
    for _ in range(5):
        t = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter() - t) / n * 1e6)
    return round(best, 2)


def _refuse_ms(payload: bytes) -> float:
    t = time.perf_counter()
    try:
        record_check.fields(record_check.parse(payload))
    except record_check.Refused:
        pass
    return round((time.perf_counter() - t) * 1e3, 2)


def main() -> None:
    target = {"position_mm": [12.5, -3.25, 201.0], "covariance_mm2": (np.eye(3) * 16).tolist(),
              "score": 0.93}
    rec = {"seq": 1, "acquisition": 1, "device_time_us": 123456789, "host_time": time.time(),
           "targets": [target] * 4, "diagnostics": {"pad": "x" * 900}}
    payload = json.dumps(rec).encode()
    key = bytes(range(32))
    tag = record_auth.attachment(key, "robot/front", payload)
    verifier = record_auth.Verifier(key, "robot/front")
    deep = b"[" * 100_000 + b"]" * 100_000
    many = json.dumps({**rec, "targets": [{"position_mm": [0, 0, 1]}] * 24_000}).encode()
    print(json.dumps({
        "record_bytes": len(payload),
        "tag_us": _per_call_us(lambda: record_auth.attachment(key, "robot/front", payload), 2000),
        "verify_us": _per_call_us(lambda: verifier._key and record_auth.tag(
            key, "robot/front", payload) == tag[4:], 2000),
        "check_us": _per_call_us(lambda: record_check.fields(record_check.parse(payload)), 2000),
        "refuse_100000_deep_ms": _refuse_ms(deep),
        "refuse_24000_targets_ms": _refuse_ms(many),
        "refuse_24000_targets_bytes": len(many),
    }, indent=1))


if __name__ == "__main__":
    main()
