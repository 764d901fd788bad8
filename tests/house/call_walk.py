"""A walk of one command's calls across the layers of docs/layers.md (issue 42).

Every Python call made by the project's code while a command runs (all threads), caller to
callee, is mapped to the callee's and the caller's package. A *climb back up* is a distinct
call edge from a package of a lower layer into one of a higher layer (a callback handed down
and called from below, e.g. the live loop calling the CLI's status line): imports cannot see
those, tests/house/test_layers.py keeps the imports. Not counted: imports (a module's body),
and calls into the virtual board (`sim`) through pyserial's URL handler or from its own code:
it stands for the hardware across the link. The *port walk* is the functions that are
handed the port URL itself as an argument (the rooms it stays in).

    python -m tests.house.call_walk run --port sim:// --frames 3 -o /dev/null
"""

from __future__ import annotations

import sys
import threading
from collections import Counter
from dataclasses import dataclass, field

from tests.house.test_layers import LAYERS

RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}
PROJECT = ("spiel_edge", "firmware_protocol")


def package(module: str | None) -> str | None:
    """spiel_edge.X.Y -> X (the root: __init__); spiel_edge.protocol sits with the foundations."""
    if not module:
        return None
    parts = module.split(".")
    if parts[0] == "firmware_protocol":
        return "_jit"  # imports nothing of the host but the project's numba decorator
    if parts[0] != "spiel_edge":
        return None
    return parts[1] if len(parts) > 1 else "__init__"


@dataclass
class Walk:
    port: str
    climbs: Counter = field(default_factory=Counter)  # (caller, callee) qualnames -> calls
    port_stays: Counter = field(default_factory=Counter)  # function given the port -> calls
    modules: set = field(default_factory=set)
    calls: Counter = field(default_factory=Counter)  # every project function -> calls

    def port_rooms(self) -> set[str]:
        return {name.rsplit(":", 1)[0] for name in self.port_stays}

    def report(self) -> str:
        lines = [
            f"port walk: {sum(self.port_stays.values())} stays in {len(self.port_rooms())} rooms "
            f"({len(self.port_stays)} functions); climbs back up: {len(self.climbs)} distinct "
            f"edges ({sum(self.climbs.values())} calls)"
        ]
        lines += [f"  port in {name} x{n}" for name, n in sorted(self.port_stays.items())]
        lines += [f"  climb {a} -> {b} x{n}" for (a, b), n in sorted(self.climbs.items())]
        return "\n".join(lines)

    def profile(self, frame, event, arg) -> None:
        if event != "call":
            return
        callee = frame.f_globals.get("__name__")
        b = package(callee)
        if b is None or frame.f_code.co_name == "<module>":
            return  # outside the project, or an import (tests/house/test_layers.py's part)
        self.modules.add(callee)
        code = frame.f_code
        name = f"{callee}:{code.co_qualname if hasattr(code, 'co_qualname') else code.co_name}"
        self.calls[name] += 1
        args = [frame.f_locals.get(v) for v in code.co_varnames[: code.co_argcount]]
        if self.port and any(isinstance(v, str) and v == self.port for v in args):
            self.port_stays[name] += 1
        caller = frame.f_back
        while caller is not None and package(caller.f_globals.get("__name__")) is None:
            caller = caller.f_back  # through the standard library and click: the project's caller
        if caller is None:
            return
        cm = caller.f_globals.get("__name__")
        a = package(cm)
        if b == "sim" and a != "sim" and _the_board(callee, caller):
            return  # the virtual board: the hardware behind the link, not a layer of the host
        if RANK.get(a, 0) < RANK.get(b, 0):
            cc = caller.f_code
            cname = f"{cm}:{getattr(cc, 'co_qualname', cc.co_name)}"
            self.climbs[(cname, name)] += 1


def _the_board(callee: str, caller) -> bool:
    """A call into the virtual board: through pyserial's URL handler (``sim.protocol_sim``, the
    link's far end), or made while the board's own code is on the stack (its thread)."""
    if callee == "spiel_edge.sim.protocol_sim":
        return True
    while caller is not None:
        if package(caller.f_globals.get("__name__")) == "sim":
            return True
        caller = caller.f_back
    return False


def walk(argv: list[str]) -> tuple[Walk, int]:
    """Run ``spiel-edge ARGV`` in this process under the walk; (the walk, its exit code)."""
    from spiel_edge.cli import main

    port = argv[argv.index("--port") + 1] if "--port" in argv else ""
    w = Walk(port)
    threading.setprofile(w.profile)
    sys.setprofile(w.profile)
    try:
        code = main(list(argv))
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    return w, code


if __name__ == "__main__":
    w, code = walk(sys.argv[1:])
    print(w.report(), file=sys.stderr)
    sys.exit(code)
