"""Fuzz the reference firmware's request decoder with libFuzzer, for a bounded count or time.

    python -m tools.release.firmware_fuzz --runs 10000000          # the figure in docs/firmware.md
    python -m tools.release.firmware_fuzz --seconds 30 --json

Builds ``make TARGET=fuzz`` (firmware_protocol/firmware/fuzz/fuzz_request.c: the portable core
with firmware update and I/Q on an in-memory HAL, clang -fsanitize=fuzzer,address,undefined),
seeds a corpus with the protocol's request vectors (test_vectors.json) and with whole firmware
updates as framed records (begin, write, verify, test, the reset into the trial image, then
confirm or a rollback), runs it and prints the harness's own input
count (it counts every call and prints it at exit), libFuzzer's, the time and the load. Exit
status 0 when the run ended without a crash or a sanitizer report, 1 when it found one (the
input is kept in the output folder, the report's summary line printed), 2 when clang or its
fuzzer runtime is missing (Debian: clang, libclang-rt-14-dev).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "firmware_protocol" / "firmware"


class FuzzError(Exception):
    """The harness could not be built or run (one line, for the user)."""


FAST = "-fno-sanitize-coverage=trace-cmp"


def build(out: Path, cc: str = "clang", fast: bool = False) -> Path:
    if shutil.which(cc) is None:
        raise FuzzError(f"{cc} not found (Debian: apt-get install clang libclang-rt-14-dev)")
    done = subprocess.run(
        [
            "make",
            "-s",
            "TARGET=fuzz",
            f"BUILD={out}",
            f"FUZZ_CC={cc}",
            f"FUZZ_COVERAGE={FAST if fast else ''}",
        ],
        cwd=FIRMWARE,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["?"])[-1]
        if "libclang_rt.fuzzer" in done.stderr or "fuzzer" in last:
            raise FuzzError(f"no libFuzzer runtime for {cc} (Debian: libclang-rt-14-dev): {last}")
        raise FuzzError(f"make TARGET=fuzz failed: {last}")
    return out / "spiel_fuzz"


# The harness's record type index (fuzz_request.c, types[]): record byte 0 picks
# FRAMED_TYPES[byte % len]. tests/firmware/test_fuzz.py checks that the two tables agree.
# fmt: off
FRAMED_TYPES: tuple[int, ...] = (
    0x0001, 0x0002, 0x0004, 0x0005, 0x0010, 0x0011, 0x0012, 0x0020, 0x0021, 0x0022, 0x0023,
    0x0003, 0x0013, 0x0006, 0x0007, 0x0008, 0x0009, 0x000A, 0x0014, 0x0024, 0x0025, 0x0030,
    0x0031, 0x0032, 0x0033, 0x0034, 0x0040, 0x8A01, 0xFFFF, 0x0041, 0x0042, 0x0043, 0x0044,
    0x0045,
)
# fmt: on
HELLO, REBOOT, FW_INFO = 0x0001, 0x0005, 0x0040
FW_BEGIN, FW_WRITE, FW_VERIFY, FW_TEST, FW_CONFIRM = 0x0041, 0x0042, 0x0043, 0x0044, 0x0045
# mode byte bits (fuzz_request.c): 1 framed records, 8 slot 0 holds a running confirmed image
FRAMED, IMAGE0 = 1, 8


def record(msg_type: int, payload: bytes = b"", seq_step: int = 1, flags: int = 0) -> bytes:
    """One framed-mode record: type index, flags, seq step, u16 length, payload."""
    return (
        bytes([FRAMED_TYPES.index(msg_type), flags, seq_step])
        + len(payload).to_bytes(2, "little")
        + payload
    )


def update_records(image: bytes, chunk: int = 200, retry: bool = False) -> bytes:
    """HELLO (version 2) and a whole upload: FW_INFO, FW_BEGIN, FW_WRITE chunks (with
    ``retry``, the first chunk sent again after the second under a new seq: answered without
    writing), FW_VERIFY, FW_TEST with no delay (the board resets into the trial image after
    it)."""
    import hashlib

    from crc32c import crc32c

    out = record(HELLO, bytes([1, 2, 0, 0, 0, 0, 0, 0])) + record(FW_INFO)
    out += record(
        FW_BEGIN,
        len(image).to_bytes(4, "little")
        + crc32c(image).to_bytes(4, "little")
        + (32).to_bytes(2, "little")
        + hashlib.sha256(image).digest(),
    )
    writes = [
        record(
            FW_WRITE,
            off.to_bytes(4, "little")
            + len(image[off : off + chunk]).to_bytes(2, "little")
            + image[off : off + chunk],
        )
        for off in range(0, len(image), chunk)
    ]
    if retry and len(writes) > 1:  # the first chunk again (a retry, PROTOCOL.md 14.3)
        writes.insert(2, writes[0])
    return out + b"".join(writes) + record(FW_VERIFY) + record(FW_TEST, (0).to_bytes(2, "little"))


def _dev_signer():
    """The development key (the fuzz build's FW_KEY), so the seeds' uploads pass FW_VERIFY;
    None (unsigned seeds, refused at FW_VERIFY) without the cryptography package."""
    try:
        from spiel_edge.device.fwkeys import load_private_key
        from spiel_edge.errors import InputError

        key = Path(__file__).resolve().parents[2] / "firmware_protocol/firmware/keys/dev.key"
        return load_private_key(key)
    except (ImportError, InputError):
        return None


def update_seeds() -> dict[str, bytes]:
    """Framed inputs that drive a whole firmware update, so the fuzzer starts deep: from the
    recovery loader (erased slots) and from a running image in slot 0, then after the reset
    into the trial image FW_CONFIRM, or a REBOOT before it (the rollback); one upload repeats
    a chunk already written (the device's retry path)."""
    from spiel_edge.protocol.image import pack_image

    image = pack_image(
        bytes(range(256)) + bytes(44), version="2.0.0+fuzz", target="posix", signer=_dev_signer()
    )
    after = record(HELLO, bytes([1, 2, 0, 0, 0, 0, 0, 0])) + record(FW_INFO)
    confirm = after + record(FW_CONFIRM) + record(FW_INFO)
    rollback = after + record(REBOOT, bytes(3)) + after
    seeds = {}
    for mode in (FRAMED, FRAMED | IMAGE0):
        header = bytes([mode, 0, 0xFF, 0])
        seeds[f"seed-fw-update-confirm-{mode}"] = header + update_records(image) + confirm
        seeds[f"seed-fw-update-rollback-{mode}"] = header + update_records(image) + rollback
        seeds[f"seed-fw-update-retry-{mode}"] = header + update_records(image, retry=True) + confirm
    return seeds


# Little-endian boundary values for the u32/u16 offsets and lengths of requests (FW_WRITE,
# CONFIG_READ/WRITE): libFuzzer's own integer mutations add small deltas, so an offset near
# 2^32 (where offset + length wraps) is otherwise three exact bytes away. Plus the image magic.
DICTIONARY: tuple[bytes, ...] = (
    b"\xff\xff\xff\xff",
    b"\xff\xff\xff",
    b"\xff\xff",
    b"\x00\x00\x00\x80",
    b"\xff\xff\xff\x7f",
    b"\x00\x00\x01\x00",
    b"\x00\x08\x00\x00",
    b"SPFW",
    b"posix",
)


def write_dictionary(path: Path) -> Path:
    """DICTIONARY as a libFuzzer -dict file (one quoted token a line, bytes as \\xNN)."""
    lines = [f'kw{i}="' + "".join(f"\\x{b:02x}" for b in t) + '"' for i, t in enumerate(DICTIONARY)]
    path.write_text("\n".join(lines) + "\n")
    return path


def seed_corpus(corpus: Path) -> int:
    """The request vectors as raw-transport inputs (mode 0) and as framed records (mode 1)."""
    from spiel_edge.protocol import load_test_vectors

    corpus.mkdir(parents=True, exist_ok=True)
    vectors = load_test_vectors()
    n = 0
    for i, v in enumerate(vectors["messages"]):
        if v["response"]:
            continue  # the device receives requests
        wire = bytes.fromhex(v["wire_hex"])
        for mode in (0, 2):  # erased flash, committed config
            name = f"seed-{i}-{v['class']}-{mode}"
            (corpus / name).write_bytes(bytes([mode, 0, 0xFF, 0]) + wire)
            n += 1
    for v in vectors["frames"]:
        if len(v.get("wire_hex", "")) < 2 * 4096:
            (corpus / f"seed-frame-{v['name']}").write_bytes(
                bytes([0, 7, 0xFF, 3]) + bytes.fromhex(v["wire_hex"])
            )
            n += 1
    for name, data in update_seeds().items():
        (corpus / name).write_bytes(data)
        n += 1
    return n


def run(
    exe: Path,
    corpus: Path,
    out: Path,
    runs: int | None,
    seconds: float | None,
    seed: int,
    max_len: int,
) -> dict:
    args = [
        str(exe),
        f"-seed={seed}",
        f"-max_len={max_len}",
        f"-dict={write_dictionary(out / 'spiel.dict')}",
        "-print_final_stats=1",
        f"-artifact_prefix={out}/",
    ]
    if runs is not None:
        args.append(f"-runs={runs}")
    if seconds is not None:
        args.append(f"-max_total_time={max(1, int(seconds))}")
    args.append(str(corpus))
    log_path = out / "fuzz.log"
    started = time.monotonic()
    load_before = os.getloadavg()[0]
    with open(log_path, "w") as log:
        status = subprocess.run(args, stdout=log, stderr=subprocess.STDOUT).returncode
    elapsed = time.monotonic() - started
    text = log_path.read_text(errors="replace")
    harness = re.findall(r"spiel_fuzz: inputs (\d+)", text)  # at exit, or every million
    interrupted = "run interrupted" in text or status in (-2, -15, 130)
    units = re.findall(r"stat::number_of_executed_units:\s*(\d+)", text)
    summary = [line for line in text.splitlines() if "SUMMARY:" in line or "runtime error" in line]
    artifacts = sorted(str(p) for p in out.glob("crash-*")) + sorted(
        str(p) for p in out.glob("leak-*")
    )
    return {
        "harness_inputs": int(harness[-1]) if harness else None,
        "libfuzzer_units": int(units[-1]) if units else None,
        "seconds": round(elapsed, 1),
        "inputs_per_s": round(int(harness[-1]) / elapsed) if harness and elapsed > 0 else None,
        "status": status,
        "interrupted": interrupted,
        "crashed": bool(artifacts) or bool(summary) or (status != 0 and not interrupted),
        "reports": summary[:5],
        "artifacts": artifacts,
        "corpus_files": sum(1 for _ in corpus.iterdir()),
        "load_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "command": " ".join(args),
        "log": str(log_path),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m tools.release.firmware_fuzz", description=__doc__
    )
    parser.add_argument("--runs", type=int, default=None, help="inputs to run (libFuzzer -runs)")
    parser.add_argument("--seconds", type=float, default=None, help="time limit in seconds")
    parser.add_argument("--corpus", type=Path, default=None, help="corpus folder (kept)")
    parser.add_argument("--out", type=Path, default=None, help="build, log and crash folder")
    parser.add_argument("--seed", type=int, default=1, help="libFuzzer's random seed")
    parser.add_argument("--max-len", type=int, default=4096, help="longest input (bytes)")
    parser.add_argument("--cc", default="clang", help="the clang to build with")
    parser.add_argument(
        "--fast",
        action="store_true",
        help="build without comparison tracing (about 3x the inputs/s; for long runs over a "
        "corpus grown without --fast)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = parser.parse_args(argv)
    if args.runs is None and args.seconds is None:
        args.runs = 100_000
    if (args.runs is not None and args.runs < 1) or (
        args.seconds is not None and args.seconds <= 0
    ):
        print("error: --runs and --seconds must be positive", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="spiel-fuzz-") as tmp:
        out = (args.out or Path(tmp)).resolve()
        out.mkdir(parents=True, exist_ok=True)
        try:
            exe = build(out / ("build-fast" if args.fast else "build"), args.cc, args.fast)
        except FuzzError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        corpus = (args.corpus or out / "corpus").resolve()
        seeds = seed_corpus(corpus)
        result = run(exe, corpus, out, args.runs, args.seconds, args.seed, args.max_len)
        result["seeds"] = seeds
        result["trace_cmp"] = not args.fast
        if args.json:
            print(json.dumps(result))
        else:
            print(
                f"spiel_fuzz: {result['harness_inputs']} inputs (harness count; libFuzzer "
                f"{result['libfuzzer_units']}) in {result['seconds']} s, "
                f"{result['inputs_per_s']}/s, load {result['load_1min']}: "
                + (
                    "CRASH " + "; ".join(result["reports"] + result["artifacts"])
                    if result["crashed"]
                    else "no crash"
                )
            )
        if result["crashed"] and args.out is None:
            keep = Path(tempfile.mkdtemp(prefix="spiel-fuzz-crash-"))
            for p in result["artifacts"] + [result["log"]]:
                shutil.copy(p, keep)
            print(f"crash inputs and the log kept in {keep}", file=sys.stderr)
    return 1 if result["crashed"] else 0


if __name__ == "__main__":
    sys.exit(main())
