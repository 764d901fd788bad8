"""A warm-up step in child processes, each within a memory budget.

numba and LLVM keep every module they compiled until the process ends (each kernel's whole
call tree, linked, as IR and as machine code; the typing of each), so one process compiling a
whole step grows to hundreds of MiB (docs/first-start.md, "Cold compile"). Here a step runs in
``python -m spiel_edge.runtime.warmup STEP``; a child whose resident size passed
:func:`budget_mib` stops just before its next kernel compiles (exit status :data:`RESTART`;
every kernel compiled so far is in the cache), naming that kernel and its signature, and a
fresh child compiles that kernel first, alone, then runs the step again, loading what the
earlier ones saved. Progress is certain: a child either compiles a kernel or hands over a
callee of the one it was handed (the call tree is finite).
"""

from __future__ import annotations

import base64
import contextlib
import importlib
import json
import logging
import os
import pickle
import signal
import subprocess
import sys
import time

log = logging.getLogger(__name__)

ENV_BUDGET = "SPIEL_EDGE_WARMUP_BUDGET_MIB"
BUDGET_MIB = 220.0
RESTART = 75  # a child's exit status: past the budget, go on in a fresh one
MAX_CHILDREN = 400  # per step: a bound, never reached (each child makes progress)


class WarmupError(RuntimeError):
    """A warm-up child process failed (its error is on stderr)."""


def run_child(step: str, progress) -> dict:
    """The step ``step`` in as many children as its budget needs: their compile reports go to
    ``progress`` (``_kernel_cache`` listener's arguments), the last child's report (its
    ``compiled`` including what the earlier children compiled) is returned."""
    compiled: set[str] = set()
    first: list[str] = []
    for _attempt in range(MAX_CHILDREN):
        report, status, first = _one_child(step, progress, compiled, first)
        if status != RESTART:
            break
    else:
        raise WarmupError(f"the warm-up step {step!r} did not finish in {MAX_CHILDREN} children")
    if status != 0 or report is None:
        raise WarmupError(f"the warm-up step {step!r} failed (exit status {status})")
    report["kernels"] = sorted(compiled | set(report["kernels"]))  # earlier children's too
    report["compiled"] = sorted(compiled | set(report["compiled"]))
    report["cache_hits"] = sorted(set(report["cache_hits"]) - compiled)
    return report


def _one_child(step: str, progress, compiled: set, first: list[str]):
    """One child of ``step`` (compiling ``first``, a kernel and its signature, before it):
    (its report or None, its exit status, the kernel to compile first in the next)."""
    cmd = [sys.executable, "-m", "spiel_edge.runtime.warmup", step, *first]
    # a session of its own: Ctrl-C on the terminal reaches this process only, which stops
    # the child below (SIGTERM: it ends by the signal's default action, no traceback)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, start_new_session=True)
    report, handover = None, []
    try:
        report, handover = _relay(proc, progress, compiled)
    finally:
        if proc.poll() is None:
            with contextlib.suppress(OSError):
                os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
    return report, proc.wait(), handover


def _relay(proc, progress, compiled: set):
    """The child's JSON lines: (its report or None, the kernel it handed over or [])."""
    report, handover = None, []
    with proc.stdout:
        for line in proc.stdout:
            try:
                message = json.loads(line)
            except ValueError:
                continue
            if "report" in message:
                report = message["report"]
            elif "handover" in message:
                handover = message["handover"]
            else:
                if message["event"] == "compiled":
                    compiled.add(message["name"])
                if progress is not None:
                    progress(message["event"], message["name"], message["detail"])
    return report, handover


def child_main(argv: list[str], warmup) -> int:
    """``STEP [KERNEL SIGNATURE [outermost]]``: compile KERNEL for SIGNATURE (pickled, base64)
    first (``outermost``: alone, its callees handed over), then
    run STEP of ``warmup`` (the module, handed in: no import cycle); each compile report and
    then the report as JSON lines on stdout. Past the budget, exit with :data:`RESTART` before
    a kernel compiles, naming it (``handover``)."""
    from spiel_edge import _kernel_cache

    out = sys.stdout
    budget = budget_mib()
    first = argv[1] if len(argv) > 2 else None
    alone = argv[3:] == ["outermost"]  # the handed kernel compiles with its callees cached
    done = {"compiled": 0, "open": 0}  # kernels compiled; compiles started, not ended

    def send(event: str, name: str, detail: object) -> None:
        if event == "compile" and _hand_over(name, first, alone, done, budget):
            signature = base64.b64encode(pickle.dumps(detail)).decode("ascii")
            outermost = "outermost" if done["open"] == 0 else "nested"
            out.write(json.dumps({"handover": [name, signature, outermost]}) + "\n")
            out.flush()
            os._exit(RESTART)  # numba's compiler holds its lock: nothing to clean up
        done["compiled"] += event == "compiled"
        done["open"] += (event == "compile") - (event == "compiled")
        value = detail if isinstance(detail, (int, float)) else str(detail)
        out.write(json.dumps({"event": event, "name": name, "detail": value}) + "\n")
        out.flush()

    _kernel_cache.listeners.append(send)
    t0 = time.perf_counter()
    if first is not None:
        try:
            module, _, attr = first.rpartition(".")
            signature = pickle.loads(base64.b64decode(argv[2]))
            getattr(importlib.import_module(module), attr).compile(signature)
        except Exception as exc:  # the step below compiles it anyway, where it is called
            log.warning("compiling %s first failed (%s): it compiles in its step", first, exc)
    {**warmup.STEPS, **warmup.EXTRA_STEPS}[argv[0]]()
    kernels = warmup.pipeline_kernels()
    report = warmup._report(t0, kernels)
    used = [n for n, k in kernels.items() if k.signatures]
    out.write(json.dumps({"report": {**report, "kernels": used}}) + "\n")
    out.flush()
    return 0


def _hand_over(name: str, first: str | None, alone: bool, done: dict, budget: float) -> bool:
    """Whether the kernel ``name``, about to compile, goes to a fresh child instead.

    - an outermost compile (a kernel called from Python: the acquisition kernels, the
      heaviest) once this child compiled anything: it starts in a fresh child;
    - there (``alone``), each of its callees not in the cache: it compiles with its callees
      loaded, not on top of their compiles;
    - any kernel once this child's resident size passed the budget (after >= 1 kernel, or
      when it is not the handed one: a fresh child always makes progress)."""
    if alone and not done["compiled"] and name != first:
        return True
    if not done["compiled"]:
        return name != first and resident_mib() > budget
    return done["open"] == 0 or resident_mib() > budget


def budget_mib() -> float:
    """The resident size (MiB) past which a warm-up child hands over to a fresh one
    (``SPIEL_EDGE_WARMUP_BUDGET_MIB``, default :data:`BUDGET_MIB`)."""
    try:
        return float(os.environ.get(ENV_BUDGET, BUDGET_MIB))
    except ValueError:
        return BUDGET_MIB


def resident_mib() -> float:
    """This process's resident size now, in MiB (0 where /proc is missing)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except OSError:
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
