"""Corruption: >= 100k random or damaged streams, every single-bit flip, resync."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.protocol import Frame, FrameDecoder, encode_frame, load_test_vectors

N_STREAMS = 100_000


def _pool(rng: np.random.Generator) -> list[Frame]:
    sizes = [0, 1, 2, 13, 253, 254, 255, 300, 1024, 4096, 8256]
    return [
        Frame(
            int(rng.integers(0, 1 << 16)),
            i,
            int(rng.integers(0, 32)),
            int(rng.integers(0, 1 << 32)),
            rng.integers(0, 256, n, dtype=np.uint8).tobytes(),
        )
        for i, n in enumerate(sizes * 3)
    ]


def _damage(wire: bytes, kind: int, rng: np.random.Generator) -> bytes:
    buf = np.frombuffer(wire, np.uint8).copy()
    if kind == 1:  # 1..4 bit flips anywhere, the delimiter included
        pos = rng.integers(0, buf.size, rng.integers(1, 5))
        buf[pos] ^= (1 << rng.integers(0, 8, pos.size)).astype(np.uint8)
        return buf.tobytes()
    if kind == 2:  # a dropped byte (not the delimiter)
        return np.delete(buf[:-1], rng.integers(0, buf.size - 1)).tobytes() + b"\x00"
    if kind == 3:  # a random non-zero byte inserted inside the frame
        at = int(rng.integers(1, buf.size))
        return np.insert(buf, at, rng.integers(1, 256)).tobytes()
    return buf[: rng.integers(1, buf.size - 1)].tobytes() + b"\x00"  # kind 4: truncated


def test_100k_corrupted_or_random_streams() -> None:
    rng = np.random.default_rng(20240601)
    pool = _pool(rng)
    wires = [f.encode() for f in pool]
    noise = rng.integers(0, 256, 4_000_000, dtype=np.uint8).tobytes()
    delivered = damaged_delivered = 0
    for i in range(N_STREAMS):
        kind = i % 6
        decoder = FrameDecoder()
        if kind == 0:  # pure random bytes, zeros included
            start = int(rng.integers(0, len(noise) - 512))
            frames = decoder.feed(noise[start : start + int(rng.integers(1, 512))])
            assert frames == []
            continue
        j = int(rng.integers(0, len(pool)))
        if kind == 5:  # garbage, delimiter, intact frame, unterminated garbage
            g = int(rng.integers(0, len(noise) - 64))
            stream = noise[g : g + 40] + b"\x00" + wires[j] + noise[g + 40 : g + 64]
            assert decoder.feed(stream) == [pool[j]]
            delivered += 1
            continue
        for frame in decoder.feed(_damage(wires[j], kind, rng)):
            damaged_delivered += 1
            assert frame == pool[j], "a damaged frame was delivered"
    assert delivered == N_STREAMS // 6
    assert damaged_delivered == 0


def _sample_frames() -> list[bytes]:
    vectors = load_test_vectors()
    frames = [bytes.fromhex(v["wire_hex"]) for v in vectors["frames"] if v["name"] != "max_payload"]
    frames += [bytes.fromhex(v["wire_hex"]) for v in vectors["messages"]]
    frames.append(encode_frame(0x13, bytes(range(256)) * 16, seq=5, flags=8, aux=77))
    return frames


@pytest.mark.parametrize("wire", _sample_frames(), ids=lambda w: f"{len(w)}B")
def test_every_single_bit_flip_is_rejected(wire: bytes) -> None:
    trailer = encode_frame(1, b"next", seq=1)
    buf = bytearray(wire)
    for bit in range(len(buf) * 8):
        buf[bit // 8] ^= 1 << (bit % 8)
        decoder = FrameDecoder()
        # \x00 closes a frame whose delimiter was flipped; the trailer must still come through.
        frames = decoder.feed(bytes(buf) + b"\x00" + trailer)
        assert [f.payload for f in frames] == [b"next"], f"bit {bit}"
        assert decoder.stats.errors >= 1
        buf[bit // 8] ^= 1 << (bit % 8)


def test_intact_frame_after_each_damage_kind() -> None:
    rng = np.random.default_rng(7)
    wire, nxt = encode_frame(2, bytes(300), seq=1), encode_frame(2, b"after", seq=2)
    for kind in (1, 2, 3, 4):
        for _ in range(200):
            damaged = _damage(wire, kind, rng)[:-1] + b"\x00"  # its delimiter survives
            frames = FrameDecoder().feed(damaged + nxt)
            assert frames[-1].payload == b"after"
            assert all(f.seq in (1, 2) for f in frames)


def test_one_kernel_call_per_read_equals_piece_by_piece(monkeypatch) -> None:
    """FrameDecoder.feed decodes every complete piece of a read in one kernel call; the same
    chunked streams (intact, damaged, oversize, empty pieces, garbage) give the same frames
    and the same counters as decoding piece by piece (no kernels)."""
    from spiel_edge.protocol import cobs
    from spiel_edge.protocol.framing import MAX_ENCODED_SIZE

    rng = np.random.default_rng(7)
    pool = [f.encode() for f in _pool(rng)]
    parts = []
    for i in range(400):
        wire = pool[int(rng.integers(0, len(pool)))]
        kind = i % 7
        if 1 <= kind <= 4:
            wire = _damage(wire, kind, rng)
        elif kind == 5:
            wire = b"\x00\x00" + rng.integers(1, 256, 40, dtype=np.uint8).tobytes()
        elif kind == 6 and i % 35 == 6:
            wire = b"\x05" * (MAX_ENCODED_SIZE + 10) + b"\x00"  # over-long
        parts.append(wire)
    stream = b"".join(parts)
    cuts = np.sort(rng.integers(0, len(stream), 300))
    reads = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]
    assert cobs.kernels() is not None

    def run() -> tuple[list[Frame], dict]:
        decoder = FrameDecoder()
        frames = [f for chunk in reads for f in decoder.feed(chunk)]
        return frames, decoder.stats.as_dict()

    batched = run()
    monkeypatch.setattr(cobs, "_kernels", None)
    assert run() == batched
    assert batched[1]["frames"] > 40 and batched[1]["oversize"] >= 1 and batched[1]["crc"] > 0
