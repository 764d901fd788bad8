"""Figures of docs/security.md: what checking and authenticating a board record costs, and
how fast `fuse` refuses the issue's hostile messages. Prints one JSON document.

    .venv/bin/python -m tools.security_figures [--sockets] [--foxglove]

--sockets: the sockets a Zenoh session can be reached on, Zenoh's defaults against ours;
--foxglove: log lines from 300 Foxglove clients connecting and leaving, limited or not.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import sys
import time

import numpy as np

from spiel_edge.outputs import record_auth
from spiel_edge.robot import record_check
from spiel_edge.robot.fusion import record_targets


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
    with contextlib.suppress(record_check.Refused):
        record_check.fields(record_check.parse(payload))
    return round((time.perf_counter() - t) * 1e3, 2)


def sockets() -> dict:
    import zenoh

    from spiel_edge.outputs.zenoh import session_config
    from tests.security._sockets import reachable

    out = {}
    for name, cfg in (("zenoh_defaults", zenoh.Config()), ("spiel_edge", session_config())):
        before = set(reachable(os.getpid()))
        session = zenoh.open(cfg)
        time.sleep(0.5)
        out[name] = sorted(f"{p} {a}:{port}" for p, a, port in set(reachable(os.getpid())) - before)
        session.close()
        time.sleep(0.5)
    return out


def foxglove_lines(limited: bool, clients: int = 300) -> int:
    """Lines the Foxglove SDK logs at -v while ``clients`` connect and go away."""
    from spiel_edge.cli import setup_logging
    from spiel_edge.outputs.foxglove import FoxgloveSink

    class Count(logging.Handler):
        n = 0

        def emit(self, record):
            Count.n += record.name.startswith("foxglove")

    setup_logging(1)
    handler = logging.getLogger().handlers[0]
    counter = Count()
    for f in handler.filters if limited else []:
        counter.addFilter(f)
    logging.getLogger().handlers = [counter]
    sink = FoxgloveSink("127.0.0.1:0")
    for i in range(clients):
        with socket.create_connection(("127.0.0.1", sink.port)) as c:
            if i % 2:
                c.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
    time.sleep(1.0)
    sink.close()
    return Count.n


def main() -> None:
    if "--sockets" in sys.argv:
        print(json.dumps(sockets(), indent=1))
        return
    if "--foxglove" in sys.argv:
        print(json.dumps({"unlimited": foxglove_lines(False), "limited": foxglove_lines(True)}))
        return
    target = {
        "position_mm": [12.5, -3.25, 201.0],
        "covariance_mm2": (np.eye(3) * 16).tolist(),
        "score": 0.93,
    }
    rec = {
        "seq": 1,
        "acquisition": 1,
        "device_time_us": 123456789,
        "host_time": time.time(),
        "targets": [target] * 4,
        "diagnostics": {"pad": "x" * 900},
    }
    payload = json.dumps(rec).encode()
    key = bytes(range(32))
    tag = record_auth.attachment(key, "robot/front", payload)
    verifier = record_auth.Verifier(key, "robot/front")
    deep = b"[" * 100_000 + b"]" * 100_000
    many = json.dumps({**rec, "targets": [{"position_mm": [0, 0, 1]}] * 24_000}).encode()
    print(
        json.dumps(
            {
                "record_bytes": len(payload),
                "tag_us": _per_call_us(
                    lambda: record_auth.attachment(key, "robot/front", payload), 2000
                ),
                "verify_us": _per_call_us(
                    lambda: (
                        verifier._key and record_auth.tag(key, "robot/front", payload) == tag[4:]
                    ),
                    2000,
                ),
                "check_us": _per_call_us(
                    lambda: record_check.fields(record_check.parse(payload)), 2000
                ),
                # what fuse did before the checks: parse, and the targets' arrays
                "unchecked_us": _per_call_us(lambda: record_targets(json.loads(payload)), 2000),
                "refuse_100000_deep_ms": _refuse_ms(deep),
                "refuse_24000_targets_ms": _refuse_ms(many),
                "refuse_24000_targets_bytes": len(many),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
