#!/usr/bin/env python3
"""stack_chain.py ELF OBJDIR [ROOT...]: the deepest stack chain of a firmware from gcc's
-fstack-usage (OBJDIR/*.su) and the direct calls in the ELF's disassembly (bl/b to a symbol;
linker veneers followed). Prints the worst chain from each ROOT (default: main and the two
interrupt handlers, which can stack on top of main's deepest point). Calls through function
pointers (TinyUSB's class driver table, the USB handler pointer) are not seen, and library
routines without a .su (newlib's memcpy, libgcc's division) count 0 (named below). The
indirect calls this firmware is known to make are added by hand (INDIRECT)."""

import re
import subprocess
import sys
from functools import cache
from pathlib import Path

# calls through pointers: the USB interrupt's handler (usb_rp2040.c), TinyUSB's CDC driver
INDIRECT = {
    "isr_irq5": {"dcd_rp2040_irq"},
    "tud_task_ext": {"cdcd_init", "cdcd_reset", "cdcd_open", "cdcd_control_xfer_cb", "cdcd_xfer_cb"},
    "process_control_request": {"cdcd_control_xfer_cb"},
}


def frames(objdir: Path) -> dict[str, int]:
    out: dict[str, int] = {}
    for su in objdir.glob("*.su"):
        for line in su.read_text().splitlines():
            loc, size, _kind = line.rsplit("\t", 2)
            name = loc.rsplit(":", 1)[-1]
            out[name] = max(out.get(name, 0), int(size))
    return out


def calls(elf: str) -> dict[str, set[str]]:
    text = subprocess.run(
        ["arm-none-eabi-objdump", "-d", elf], capture_output=True, text=True, check=True
    ).stdout
    graph: dict[str, set[str]] = {}
    current = None
    for line in text.splitlines():
        head = re.match(r"^[0-9a-f]+ <([^>]+)>:$", line)
        if head:
            current = head.group(1)
            graph.setdefault(current, set())
            continue
        call = re.search(r"\s(?:bl|b|b\.n|b\.w)\s+[0-9a-f]+ <([^>+]+)>", line)
        if current and call and call.group(1) != current:
            graph[current].add(call.group(1))
    for name, extra in INDIRECT.items():
        graph.setdefault(name, set()).update(extra)
    for name, targets in graph.items():  # a veneer calls what its name says
        veneer = re.match(r"^__(.+)_veneer$", name)
        if veneer:
            targets.add(veneer.group(1))
    return graph


def main(argv: list[str]) -> int:
    elf, objdir = argv[1], Path(argv[2])
    roots = argv[3:] or ["main", "isr_irq5", "isr_irq0"]
    size, graph = frames(objdir), calls(elf)
    missing: set[str] = set()

    @cache
    def worst(fn: str, depth: int = 0) -> tuple[int, tuple[str, ...]]:
        if fn not in size:
            missing.add(fn)
        best: tuple[int, tuple[str, ...]] = (0, ())
        if depth < 64:
            for callee in graph.get(fn, ()):
                best = max(best, worst(callee, depth + 1))
        return size.get(fn, 0) + best[0], (fn, *best[1])

    totals = []
    for root in roots:
        total, chain = worst(root)
        totals.append(total)
        print(f"{root}: {total} B: " + " -> ".join(f"{f} {size.get(f, 0)}" for f in chain))
    # an interrupt stacks on the deepest point of main: 32 bytes of exception frame each
    print(f"worst: {totals[0] + sum(t + 32 for t in totals[1:])} B (main + every handler + frames)")
    print("no .su (counted 0): " + ", ".join(sorted(missing - {"main"})[:12]) + ", ...")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
