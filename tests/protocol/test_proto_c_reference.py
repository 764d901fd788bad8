"""The C reference (firmware_protocol/c) compiled with the system compiler, checked against
the test vectors and differentially against the Python decoder."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spiel_edge.protocol import MAX_PAYLOAD, FrameDecoder, cobs, encode_frame, load_test_vectors
from spiel_edge.protocol.framing import HEADER, crc32c
from tests.protocol.c_driver import hx, run

VECTORS = load_test_vectors()


def py_decode(wire: bytes) -> list[str]:
    decoder = FrameDecoder()
    lines = [
        f"frame {f.flags} {f.msg_type} {f.seq} {f.aux} {hx(f.payload)}" for f in decoder.feed(wire)
    ]
    s = decoder.stats
    return lines + [
        f"stats {s.frames} {s.crc} {s.cobs} {s.length} {s.oversize} {s.version} {s.flags}"
    ]


def test_crc32c_matches(driver: Path) -> None:
    rng = np.random.default_rng(1)
    blobs = [b"123456789", b""] + [rng.bytes(int(n)) for n in rng.integers(0, 3000, 50)]
    got = run(driver, [f"crc {hx(b)}" for b in blobs])
    assert got == [f"crc {crc32c(b):08x}" for b in blobs]
    assert got[0] == "crc e3069283"


def test_cobs_encoding_is_byte_identical(driver: Path) -> None:
    rng = np.random.default_rng(2)
    blobs = [b"\x01" * n for n in range(0, 600)] + [bytes(n) for n in range(0, 10)]
    blobs += [rng.integers(0, 3, int(n), dtype=np.uint8).tobytes() for n in range(0, 1200, 7)]
    got = run(driver, [f"cobs {hx(b)}" for b in blobs])
    assert got == [f"cobs {hx(cobs.encode(b))}" for b in blobs]


def test_header_pack_unpack(driver: Path) -> None:
    fields = [(1, 0xFE, 0x1234, 0x5678, 0x9ABC, 0xDEADBEEF), (2, 0, 0, 0xFFFF, 0, 1)]
    got = run(driver, [f"hdr {HEADER.pack(*f).hex()}" for f in fields])
    assert got == [f"hdr {' '.join(map(str, f))} {HEADER.pack(*f).hex()}" for f in fields]


def test_encode_matches_vectors(driver: Path) -> None:
    cases = [
        (v["flags"], v["msg_type"], v["seq"], v["aux"], v["payload_hex"] or "-", v["wire_hex"])
        for v in VECTORS["frames"]
    ]
    for v in VECTORS["messages"]:
        frame = FrameDecoder().feed(bytes.fromhex(v["wire_hex"]))[0]
        cases.append(
            (frame.flags, frame.msg_type, frame.seq, frame.aux, hx(frame.payload), v["wire_hex"])
        )
    got = run(driver, [f"enc {f} {t} {s} {a} {p}" for f, t, s, a, p, _ in cases])
    assert got == [f"enc {w}" for *_, w in cases]


def test_encode_rejects_bad_input(driver: Path) -> None:
    got = run(driver, [f"enc 0 1 0 0 {bytes(MAX_PAYLOAD + 1).hex()}", "enc 32 1 0 0 -"])
    assert got == ["enc error", "enc error"]


def test_decode_matches_vectors(driver: Path) -> None:
    wires = [bytes.fromhex(v["wire_hex"]) for v in VECTORS["frames"] + VECTORS["messages"]]
    wires += [bytes.fromhex(v["wire_hex"]) for v in VECTORS["invalid"]]
    wires.append(bytes.fromhex(VECTORS["stream"]["wire_hex"]))
    got = run(driver, [f"dec {hx(w)}" for w in wires])
    assert got == [line for w in wires for line in py_decode(w)]
    for v in VECTORS["invalid"]:
        assert py_decode(bytes.fromhex(v["wire_hex"]))[0].startswith("stats 0")


def test_decoder_differential_on_damaged_streams(driver: Path) -> None:
    rng = np.random.default_rng(3)
    streams = []
    for i in range(1500):
        frames = [
            encode_frame(
                int(rng.integers(0, 65536)),
                rng.bytes(int(rng.integers(0, 700))),
                seq=i & 0xFFFF,
                flags=int(rng.integers(0, 32)),
            )
            for _ in range(int(rng.integers(1, 4)))
        ]
        buf = np.frombuffer(b"".join(frames), np.uint8).copy()
        pos = rng.integers(0, buf.size, int(rng.integers(0, 4)))
        buf[pos] ^= rng.integers(1, 256, pos.size).astype(np.uint8)
        streams.append(rng.bytes(int(rng.integers(0, 30))) + buf.tobytes())
    streams.append(b"\x01" * (3 * MAX_PAYLOAD) + b"\x00" + encode_frame(1, b"after"))
    got = run(driver, [f"dec {hx(s)}" for s in streams])
    assert got == [line for s in streams for line in py_decode(s)]
