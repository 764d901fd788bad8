"""FrameDecoder throughput with our COBS against the ``cobs`` package's C extension.

    .venv/bin/python -m tools.bench.bench_cobs        (pip install cobs first, for the comparison)

Best of 300 bursts (16 frames of 4 KB payload each, CRC and header checks included), both
implementations in one process: on a shared machine a long loop measures the sharing.
Prints one JSON object, MB/s of wire bytes per payload kind and implementation.
"""

from __future__ import annotations

import json
import os
import time
from types import SimpleNamespace

from spiel_edge.data import load_subset
from spiel_edge.protocol import cobs as ours
from spiel_edge.protocol import framing
from spiel_edge.protocol.framing import FrameDecoder, encode_frame


def _c_extension():
    try:
        from cobs import cobs as cext
    except ImportError:
        return None
    return SimpleNamespace(
        encode=cext.encode,
        decode=cext.decode,
        CobsDecodeError=cext.DecodeError,
        warm_up=lambda: None,
    )


def _best_mbps(stream: bytes, frames: int, bursts: int = 300) -> float:
    best = float("inf")
    for _ in range(bursts):
        decoder = FrameDecoder()
        t0 = time.perf_counter()
        assert len(decoder.feed(stream)) == frames
        best = min(best, time.perf_counter() - t0)
    return round(len(stream) / best / 1e6)


def main() -> dict:
    samples = load_subset().frames
    kinds = {
        "random": [os.urandom(4096) for _ in range(16)],
        "samples": [samples[i : i + 8].tobytes()[:4096] for i in range(16)],
    }
    impls = {"spiel_edge.protocol.cobs": ours, "cobs C extension": _c_extension()}
    result = {}
    try:
        for kind, payloads in kinds.items():
            stream = b"".join(encode_frame(0x13, p, seq=i, flags=8) for i, p in enumerate(payloads))
            for name, impl in impls.items():
                if impl is not None:
                    framing.cobs = impl
                    result[f"{kind} {name} MBps"] = _best_mbps(stream, len(payloads))
    finally:
        framing.cobs = ours
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
