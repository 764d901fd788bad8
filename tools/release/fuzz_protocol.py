"""Fuzz the spiel_edge.protocol decoders (framing, messages, reassembly).

With atheris installed (``pip install atheris``) this is a libFuzzer target:
    .venv/bin/python -m tools.release.fuzz_protocol -atheris_runs=1000000
Otherwise a plain random loop mutating valid frames and random bytes:
    .venv/bin/python -m tools.release.fuzz_protocol --iterations 200000 [--seed 1]
Only ProtocolError may come out of message decoding; nothing may escape ``feed``.
"""

from __future__ import annotations

import argparse
import json
import random
import sys

from spiel_edge.protocol import (
    MAX_ENCODED_SIZE,
    AcquisitionAssembler,
    FrameDecoder,
    ProtocolError,
    StreamData,
    decode_message,
    load_test_vectors,
)


def one_input(data: bytes) -> None:
    """The fuzz target: split ``data`` at a data-chosen point and decode everything."""
    cut = data[0] * len(data) // 256 if data else 0
    decoder, assembler = FrameDecoder(), AcquisitionAssembler()
    frames = decoder.feed(data[:cut]) + decoder.feed(data[cut:])
    assert decoder.buffered <= MAX_ENCODED_SIZE
    for frame in frames:
        assert FrameDecoder().feed(frame.encode()) == [frame]
        try:
            msg = decode_message(frame)
        except ProtocolError:
            continue
        if isinstance(msg, StreamData):
            assembler.feed(msg, frame.aux)


def _seeds() -> list[bytes]:
    vectors = load_test_vectors()
    return [bytes.fromhex(v["wire_hex"]) for v in vectors["messages"] + vectors["frames"]]


def _mutate(rng: random.Random, seeds: list[bytes]) -> bytes:
    buf = bytearray(b"".join(rng.choice(seeds) for _ in range(rng.randint(1, 3))))
    for _ in range(rng.randint(0, 4)):
        op, at = rng.randrange(4), rng.randrange(len(buf))
        if op == 0:
            buf[at] ^= 1 << rng.randrange(8)
        elif op == 1:
            buf[at] = rng.randrange(256)
        elif op == 2:
            del buf[at]
        else:
            buf.insert(at, rng.randrange(256))
    return bytes(buf)


def random_loop(iterations: int, seed: int) -> dict:
    rng, seeds = random.Random(seed), _seeds()
    for _ in range(iterations):
        if rng.random() < 0.25:
            one_input(rng.randbytes(rng.randint(0, 600)))
        else:
            one_input(_mutate(rng, seeds))
    return {"mode": "random", "iterations": iterations, "seed": seed, "failures": 0}


def main(argv: list[str] | None = None) -> int:
    try:
        import atheris  # type: ignore[import-not-found]
    except ImportError:
        atheris = None
    argv = sys.argv[1:] if argv is None else argv
    if atheris is not None and not any(a.startswith("--") for a in argv):
        atheris.Setup([sys.argv[0], *argv], one_input)
        atheris.Fuzz()
        return 0
    ap = argparse.ArgumentParser(description="random-loop fuzzer (atheris not installed)")
    ap.add_argument("--iterations", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    print(json.dumps(random_loop(args.iterations, args.seed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
