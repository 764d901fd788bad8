"""Flash, stack and time of the firmware's Ed25519 verification (vendor/monocypher, trimmed):
on the host (``cc -O2``, the mean of --repeat verifications), and on a Cortex-M0+ and a
Cortex-M4 (``arm-none-eabi-gcc -Os``): flash of the linked verifier (``arm-none-eabi-size`` of
a bare program that only verifies), its deepest stack frame (``-fstack-usage``) and the
instructions one verification executes under ``qemu-system-arm -icount shift=0`` (the M0+ code
runs on ``-M microbit``, a Cortex-M0 with the same ARMv6-M instruction set; the M4 code on
``-M mps2-an386``). qemu counts instructions, not cycles: on these cores most instructions take
one cycle, loads and taken branches two, so cycles are about 1.0-1.5 times the count.

    python tools/bench/bench_ed25519.py [--repeat 2000] [--json]

Needs cc; arm-none-eabi-gcc, newlib and qemu-system-arm for the MCU figures (skipped, named,
without them); the cryptography package (extra ``sign``) to sign the header it verifies.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
VENDOR = ROOT / "firmware_protocol" / "firmware" / "vendor" / "monocypher"
HERE = Path(__file__).resolve().parent
SOURCES = [VENDOR / "monocypher.c", VENDOR / "monocypher-ed25519.c"]
CORES = {
    # name: (gcc flags, qemu machine, timer Hz, define)
    "cortex-m0plus": (["-mcpu=cortex-m0plus", "-mthumb"], "microbit", 16_000_000, "BENCH_MICROBIT"),
    "cortex-m4": (
        ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16"],
        "mps2-an386",
        25_000_000,
        "BENCH_MPS2",
    ),
}
LINKER = """MEMORY { FLASH (rx) : ORIGIN = 0, LENGTH = 256K
         RAM (rwx) : ORIGIN = 0x20000000, LENGTH = 16K }
SECTIONS {
  .text : { KEEP(*(.vectors)) *(.text*) *(.rodata*) } > FLASH
  .data : { *(.data*) } > RAM AT > FLASH
  .bss : { *(.bss*) *(COMMON) } > RAM
  _estack = ORIGIN(RAM) + LENGTH(RAM);
}
"""


def write_vectors(out: Path) -> bytes:
    """bench_vec.h: the development key, a signed image's 96-byte header and its signature."""
    from spiel_edge.device.fwkeys import load_private_key
    from spiel_edge.protocol.image import pack_image

    key = load_private_key(ROOT / "firmware_protocol/firmware/keys/dev.key")
    image = pack_image(bytes(range(256)) * 4, version="bench", target="posix", signer=key)
    parts = {"bench_pk": key.public_key, "bench_msg": image[:96], "bench_sig": image[-64:]}
    text = "#include <stdint.h>\n" + "".join(
        f"static const uint8_t {name}[{len(v)}] = {{{', '.join(str(b) for b in v)}}};\n"
        for name, v in parts.items()
    )
    (out / "bench_vec.h").write_text(text)
    return image


def host(work: Path, repeat: int) -> dict:
    exe = work / "ed25519_driver"
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    src = ROOT / "tests" / "firmware" / "ed25519_driver.c"
    subprocess.run(
        [cc, "-std=c99", "-O2", f"-I{VENDOR}", str(src), *map(str, SOURCES), "-o", str(exe)],
        check=True,
    )
    image = write_vectors(work)
    from spiel_edge.protocol.signing import DEV_PUBLIC_KEY

    line = f"{DEV_PUBLIC_KEY.hex()} {image[:96].hex()} {image[-64:].hex()}\n"
    out = subprocess.run(
        [str(exe), "--bench", str(repeat)], input=line, capture_output=True, text=True, check=True
    )
    ok, us = out.stdout.split()
    assert ok == "0", "the host verifier refused the benchmark's signature"
    return {"compiler": "cc -O2 (x86-64)", "verify_us": float(us), "repeat": repeat}


def mcu(work: Path, core: str) -> dict:
    flags, machine, hz, define = CORES[core]
    gcc = shutil.which("arm-none-eabi-gcc")
    if not gcc:
        return {"skipped": "arm-none-eabi-gcc missing (Debian: gcc-arm-none-eabi)"}
    (work / "bench.ld").write_text(LINKER)
    elf = work / f"bench-{core}.elf"
    cmd = [
        gcc,
        *flags,
        "-std=c99",
        "-Os",
        "-ffunction-sections",
        "-fdata-sections",
        "-fstack-usage",
    ]
    cmd += [f"-D{define}", f"-I{VENDOR}", f"-I{work}", "-nostartfiles", "--specs=nano.specs"]
    cmd += ["-Wl,--gc-sections", f"-T{work / 'bench.ld'}", str(HERE / "ed25519_mcu.c")]
    subprocess.run([*cmd, *map(str, SOURCES), "-o", str(elf)], check=True, cwd=work)
    size = subprocess.run(
        ["arm-none-eabi-size", "-A", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    sections = {m[0]: int(m[1]) for m in re.findall(r"^(\.\w+)\s+(\d+)", size, re.M)}
    nm = subprocess.run(
        ["arm-none-eabi-nm", "-S", "-t", "d", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    bench_own = sum(
        int(m[0])
        for m in re.findall(
            r"^\d+ (\d+) [tT] (reset_handler|put_u32|put_s|uart_\w+|timer_\w+)$", nm, re.M
        )
    )
    frames = {}
    for su in work.glob("*.su"):
        for fn, n in re.findall(r":\d+:\d+:(\w+)\s+(\d+)", su.read_text()):
            frames[fn] = max(frames.get(fn, 0), int(n))
    result = {
        "compiler": f"arm-none-eabi-gcc {' '.join(flags)} -Os, linked with --gc-sections",
        "flash_bytes": sections.get(".text", 0) + sections.get(".data", 0),
        "of_which_benchmark_code": bench_own + 8,
        "ram_static_bytes": sections.get(".data", 0) + sections.get(".bss", 0),
        "largest_frames": dict(sorted(frames.items(), key=lambda kv: -kv[1])[:3]),
    }
    qemu = shutil.which("qemu-system-arm")
    if not qemu:
        result["time"] = "skipped: qemu-system-arm missing (Debian: qemu-system-arm)"
        return result
    proc = subprocess.Popen(
        [
            qemu,
            "-M",
            machine,
            "-icount",
            "shift=0",
            "-display",
            "none",
            "-monitor",
            "none",
            "-serial",
            "stdio",
            "-kernel",
            str(elf),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        start = time.monotonic()
        line = ""
        while "ticks=" not in line and time.monotonic() - start < 300:
            line = proc.stdout.readline()
    finally:
        proc.kill()
        proc.wait()
    m = re.search(r"ok=(\d) ticks=(\d+)", line)
    if not m or m[1] != "1":
        raise SystemExit(f"{core}: the benchmark did not verify ({line!r})")
    instructions = int(m[2]) * 1_000_000_000 // hz
    result.update(
        instructions=instructions,
        qemu=f"-M {machine} -icount shift=0, timer at {hz} Hz",
        ms_at_125MHz_cpi_1_to_1_5=[
            round(instructions / 125e3, 1),
            round(1.5 * instructions / 125e3, 1),
        ],
        ms_at_64MHz_cpi_1_to_1_5=[
            round(instructions / 64e3, 1),
            round(1.5 * instructions / 64e3, 1),
        ],
    )
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=2000, help="host verifications to average")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        figures = {"host": host(work, args.repeat)}
        for core in CORES:
            figures[core] = mcu(work, core)
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        for name, f in figures.items():
            print(name, json.dumps(f))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
