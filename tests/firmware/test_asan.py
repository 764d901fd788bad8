"""The posix firmware built with -fsanitize=address,undefined (``make TARGET=posix-asan``),
driven over stdin/stdout by a hostile host: frames cut, doubled, reordered, with a valid CRC
but lying lengths (in the header and inside the payloads), oversized, with unknown types and
flags, and garbage. The board answers with an error or drops the frame, never hangs (a probe
after every ten batches is answered) and never crashes: 0 sanitizer reports (halt_on_error;
AddressSanitizer writes to a log path that must stay empty, gcc's UndefinedBehaviorSanitizer
to stderr, which must hold no report; the exit status after EOF must be 0).

Always runs where the system compiler has the sanitizer runtimes (gcc: libasan, libubsan);
skipped with that reason otherwise."""

from __future__ import annotations

import os
import struct
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from spiel_edge.protocol import FrameDecoder, decode_message, encode_frame
from spiel_edge.protocol.framing import wrap_body
from tests.firmware.firmware import FIRMWARE

KNOWN_FLAGS = 0x1F
HEADER = struct.Struct("<BBHHHI")
# request types a hostile host may send; REBOOT is left out (it would end the session)
REQUESTS = [0x0001, 0x0002, 0x0004, 0x0010, 0x0011, 0x0012, 0x0020, 0x0021, 0x0022, 0x0023]
NOT_REQUESTS = [0x0000, 0x0003, 0x0013, 0x00FF, 0x7FFF, 0x8A01, 0xFFFF]


@pytest.fixture(scope="session")
def asan_exe(tmp_path_factory) -> Path:
    build = tmp_path_factory.mktemp("posix-asan")
    done = subprocess.run(
        ["make", "-s", "TARGET=posix-asan", f"BUILD={build}"],
        cwd=FIRMWARE,
        capture_output=True,
        text=True,
        timeout=300,
    )
    if done.returncode != 0:
        if "asan" in done.stderr or "ubsan" in done.stderr or "sanitize" in done.stderr:
            pytest.skip(f"the C compiler has no sanitizer runtime: {done.stderr.strip()[-300:]}")
        pytest.fail(f"make TARGET=posix-asan failed:\n{done.stderr}")
    return build / "spiel_fw_posix"


class AsanBoard:
    """The sanitized firmware on pipes; every byte it writes is decoded on a thread."""

    def __init__(self, exe: Path, scans: Path, flash: Path, logs: Path) -> None:
        env = dict(os.environ)
        env["ASAN_OPTIONS"] = f"halt_on_error=1:abort_on_error=0:log_path={logs}/asan"
        env["UBSAN_OPTIONS"] = f"halt_on_error=1:print_stacktrace=1:log_path={logs}/ubsan"
        self.proc = subprocess.Popen(
            [str(exe), "--scans", str(scans), "--flash", str(flash)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
        )
        self.decoder = FrameDecoder()
        self.frames: list = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        fd = self.proc.stdout.fileno()
        while True:
            data = os.read(fd, 65536)
            if not data:
                return
            got = self.decoder.feed(data)
            with self._lock:
                self.frames.extend(got)

    def send(self, data: bytes) -> None:
        self.proc.stdin.write(data)
        self.proc.stdin.flush()

    def probe(self, seq: int, timeout: float = 20.0) -> None:
        """A PING with a unique body must come back: the board is alive and in sync."""
        body = struct.pack("<I", seq) + b"probe"
        self.send(b"\x00" + encode_frame(0x0004, struct.pack("<H", len(body)) + body, seq=seq))
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                for f in self.frames:
                    if f.msg_type == 0x0004 and f.seq == seq and f.payload[2:] == body:
                        return
            assert self.proc.poll() is None, f"the firmware died: {self.stderr()}"
            time.sleep(0.005)
        raise AssertionError(f"probe {seq}: no answer within {timeout} s (a hang?)")

    def stderr(self) -> str:
        return (
            self.proc.stderr.read().decode(errors="replace") if self.proc.poll() is not None else ""
        )

    def close(self) -> int:
        """Close stdin (the firmware exits on EOF, running the sanitizers' exit checks)."""
        self.proc.stdin.close()
        status = self.proc.wait(30)
        self._reader.join(10)
        return status


def lying_frame(msg_type: int, payload: bytes, payload_len: int, seq: int, flags: int = 0) -> bytes:
    """A frame whose CRC is valid but whose header states ``payload_len``."""
    return wrap_body(HEADER.pack(1, flags, msg_type, seq, payload_len & 0xFFFF, 0) + payload)


def u16(v: int) -> bytes:
    return struct.pack("<H", v & 0xFFFF)


def u32(v: int) -> bytes:
    return struct.pack("<I", v & 0xFFFFFFFF)


def hostile_batches(rng: np.random.Generator):
    """(name, bytes) batches; each is followed by a probe."""
    seq = 100

    def nseq() -> int:
        nonlocal seq
        seq = (seq + 1) & 0xFFFF
        return seq

    valid = [
        encode_frame(0x0001, bytes([1, 2]) + u16(1024) + u32(0), seq=nseq()),
        encode_frame(0x0002, seq=nseq()),
        encode_frame(0x0004, u16(5) + b"hello", seq=nseq()),
        encode_frame(0x0012, seq=nseq()),
        encode_frame(0x0023, seq=nseq()),
        encode_frame(0x0020, b"\x00" + u32(0) + u16(256), seq=nseq()),
        encode_frame(0x0021, u32(0) + u16(16) + bytes(range(16)), seq=nseq()),
        encode_frame(0x0020, b"\x01" + u32(0) + u16(64), seq=nseq()),
        encode_frame(0x0010, u32(3) + struct.pack("<f", 200.0) + u16(64) + b"\x00\x00", seq=nseq()),
        encode_frame(0x0011, seq=nseq()),
    ]
    yield "valid requests", b"".join(valid)
    # cut: every frame truncated at random points, then the delimiter
    for w in valid:
        for cut in sorted(set(rng.integers(1, len(w) - 1, 6).tolist())):
            yield "cut", w[:cut] + b"\x00"
    # cut without a delimiter: the next frame merges with it
    yield "cut-merged", valid[2][:7] + valid[2]
    # doubled: whole frames twice (the same seq: a retry), and every byte doubled
    for w in valid:
        yield "doubled", w + w
        yield "bytes doubled", bytes(b for b in w[:-1] for _ in (0, 1)) + b"\x00"
    # reordered: the pieces of a sequence of frames shuffled, and a config transfer whose
    # chunks arrive out of order and repeated
    pieces = [w[i : i + 5] for w in valid for i in range(0, len(w), 5)]
    for _ in range(20):
        order = rng.permutation(len(pieces))
        yield "reordered pieces", b"".join(pieces[i] for i in order) + b"\x00"
    chunks = [
        encode_frame(0x0021, u32(off) + u16(100) + bytes([off % 251] * 100), seq=nseq())
        for off in range(0, 1000, 100)
    ]
    for _ in range(10):
        order = rng.permutation(len(chunks))
        commit = encode_frame(0x0022, u32(1000) + u32(int(rng.integers(0, 1 << 32))), seq=nseq())
        yield "reordered config", b"".join(chunks[i] for i in order) + commit
    # valid CRC, lying header lengths
    for t in REQUESTS:
        payload = rng.integers(0, 256, int(rng.integers(0, 40)), dtype=np.uint8).tobytes()
        for lie in (0, 1, len(payload) - 1, len(payload) + 1, 1024, 8256, 0xFFFF):
            if lie != len(payload):
                yield "lying header length", lying_frame(t, payload, lie, nseq())
    # valid frames whose payload fields lie about their own lengths
    lies = []
    for n in (0, 1, 2, 3, 1021, 1022, 1023, 1024, 0x7FFF, 0xFFFF):
        lies.append(encode_frame(0x0004, u16(n) + b"x" * min(n, 3), seq=nseq()))  # PING
        lies.append(encode_frame(0x0021, u32(0) + u16(n) + b"y" * 4, seq=nseq()))  # CONFIG_WRITE
        lies.append(encode_frame(0x0021, u32(0xFFFFFFFF - 2) + u16(n) + b"y" * 4, seq=nseq()))
        lies.append(encode_frame(0x0021, u32(4000 + n) + u16(4) + b"zzzz", seq=nseq()))
        lies.append(encode_frame(0x0020, b"\x00" + u32(n) + u16(0xFFFF), seq=nseq()))
        lies.append(encode_frame(0x0020, b"\x01" + u32(0xFFFFFFF0) + u16(n), seq=nseq()))
        lies.append(encode_frame(0x0020, bytes([n & 0xFF]) + u32(0) + u16(n), seq=nseq()))
        lies.append(encode_frame(0x0022, u32(n) + u32(0), seq=nseq()))
        lies.append(encode_frame(0x0022, u32(0xFFFFFFFF - n) + u32(0), seq=nseq()))
        lies.append(encode_frame(0x0001, bytes([n & 0xFF, (n >> 8) & 0xFF]) + u16(n), seq=nseq()))
        for rate in (0.0, -1.0, float("nan"), float("inf"), 1e30, 1e-30):
            start = u32(n) + struct.pack("<f", rate) + u16(n) + bytes([n & 3, n & 0xFF])
            lies.append(encode_frame(0x0010, start, seq=nseq()))
            lies.append(encode_frame(0x0011, seq=nseq()))
    for i in range(0, len(lies), 8):
        yield "lying payload fields", b"".join(lies[i : i + 8])
    # every request type with every short payload length, and random payloads
    for t in REQUESTS + NOT_REQUESTS:
        for n in range(0, 40):
            body = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
            yield (
                "random payload",
                encode_frame(t, body, seq=nseq()) + encode_frame(0x0011, seq=nseq()),
            )
    # larger than the board's max_payload, up to the protocol's maximum
    for n in (1019, 1024, 1025, 2048, 4097, 8256):
        for t in (0x0004, 0x0021, 0x0001):
            yield (
                "oversized",
                encode_frame(t, rng.integers(0, 256, n, dtype=np.uint8).tobytes(), seq=nseq()),
            )
    # responses, stream frames, NACKs from the host; ACK_REQUEST and MORE on requests
    for flags in range(1, KNOWN_FLAGS + 1):
        yield "flags", encode_frame(int(rng.choice(REQUESTS)), b"\x01\x02", seq=nseq(), flags=flags)
    # garbage: random bytes with zeros, long runs without a zero (> the largest piece),
    # delimiters only, 0xFF floods, a wrong version with a valid CRC
    for n in (1, 16, 255, 4096, 20000):
        yield "garbage", rng.integers(0, 256, n, dtype=np.uint8).tobytes() + b"\x00"
        yield "no delimiter", rng.integers(1, 256, n, dtype=np.uint8).tobytes()
    yield "delimiters", b"\x00" * 5000
    yield "0xff flood", b"\xff" * 9000 + b"\x00"
    for version in (0, 2, 3, 255):
        yield "version", wrap_body(HEADER.pack(version, 0, 0x0004, nseq(), 2, 0) + u16(0))
    for _ in range(200):
        w = bytearray(valid[int(rng.integers(0, len(valid)))])
        for pos in rng.integers(0, len(w), int(rng.integers(1, 6))):
            w[pos] = int(rng.integers(0, 256))
        yield "bit damage", bytes(w) + b"\x00"


def test_sanitized_firmware_survives_the_hostile_host(asan_exe, subset_scans, tmp_path):
    logs = tmp_path / "sanitizer-logs"
    logs.mkdir()
    board = AsanBoard(asan_exe, subset_scans, tmp_path / "flash.bin", logs)
    try:
        board.probe(1)
        batches = 0
        kinds: dict[str, int] = {}
        for i, (kind, data) in enumerate(hostile_batches(np.random.default_rng(2024))):
            board.send(data)
            kinds[kind] = kinds.get(kind, 0) + 1
            batches += 1
            if i % 10 == 0:
                board.probe(50000 + i)
        board.probe(2)
        # the board still works: a full handshake and a short stream of the recordings
        board.send(
            encode_frame(0x0011, seq=3)
            + encode_frame(0x0010, u32(2) + u32(0) + u16(64) + b"\x00\x00", seq=4)
        )
        board.probe(5)
        status = board.close()
    finally:
        if board.proc.poll() is None:
            board.proc.kill()  # only if an assertion stopped us: the process we started
            board.proc.wait(10)
    err = board.proc.stderr.read().decode(errors="replace")
    reports = sorted(p.name for p in logs.iterdir())
    assert reports == [], f"sanitizer reports: {reports}\n" + "\n".join(
        (logs / r).read_text()[:3000] for r in reports
    )
    assert "runtime error" not in err and "Sanitizer" not in err, err
    assert status == 0, f"exit status {status}: {err[-2000:]}"
    assert batches > 1000 and len(kinds) >= 15, kinds
    answered = [f for f in board.frames if f.flags & 0x01]  # RESPONSE
    errors = [decode_message(f) for f in answered if f.flags & 0x02]  # NACK: ERROR payloads
    assert len(answered) > 500 and len(errors) > 100  # it answered, with error codes
    assert {e.code for e in errors} >= {3, 7, 8}  # INVALID, TOO_LARGE, UNSUPPORTED
