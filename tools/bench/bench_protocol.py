"""Benchmark the spiel_edge.protocol frame decoder; prints one JSON object.

    .venv/bin/python -m tools.bench.bench_protocol [--frames 20000] [--payload 4096] [--chunk 65536]

Throughput is wire bytes per second through ``FrameDecoder.feed`` (COBS decode + CRC-32C +
header checks), fed in ``--chunk``-sized reads as a USB/serial reader would.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

from spiel_edge.protocol import FrameDecoder, StreamData, cobs, encode_frame, encode_message
from spiel_edge.protocol.messages import decode_message


def _time(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20_000)
    ap.add_argument("--payload", type=int, default=4096)
    ap.add_argument("--chunk", type=int, default=65536)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)

    payloads = [os.urandom(args.payload) for _ in range(64)]
    stream = b"".join(
        encode_frame(0x13, payloads[i % 64], seq=i & 0xFFFF, flags=8, aux=i)
        for i in range(args.frames)
    )
    chunks = [stream[i : i + args.chunk] for i in range(0, len(stream), args.chunk)]

    def decode() -> None:
        decoder = FrameDecoder()
        n = sum(len(decoder.feed(c)) for c in chunks)
        assert n == args.frames and decoder.stats.errors == 0

    decode_s = _time(decode, args.repeat)
    encode_s = _time(
        lambda: [encode_frame(0x13, p, flags=8) for p in payloads * (args.frames // 64)],
        args.repeat,
    )
    msg = StreamData(1, 0, 4, 1, 400_000, 0, payloads[0][: args.payload // 2 * 2])
    wire = encode_message(msg)
    frame = FrameDecoder().feed(wire)[0]
    n_msg = 20_000
    msg_s = _time(lambda: [decode_message(frame) for _ in range(n_msg)], args.repeat)
    result = {
        "frames": args.frames,
        "payload_bytes": args.payload,
        "chunk_bytes": args.chunk,
        "wire_bytes": len(stream),
        "decode_MBps": round(len(stream) / decode_s / 1e6, 1),
        "decode_frames_per_s": round(args.frames / decode_s),
        "encode_MBps": round(
            len(stream) / args.frames * 64 * (args.frames // 64) / encode_s / 1e6, 1
        ),
        "stream_data_decode_msgs_per_s": round(n_msg / msg_s),
        "cobs_numba": cobs.kernels() is not None,
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
