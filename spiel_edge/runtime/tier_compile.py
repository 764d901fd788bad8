"""The background compile of a tiered start: ``python -m spiel_edge.runtime.tier_compile PLAN``.

PLAN is a pickle of ``[(module, attribute, argument types), ...]``: the calls from Python into
kernels that a command made on the interpreted tier (``spiel_edge._tiers``). This process
(the supervisor) holds a lock in the cache folder (one compile at a time per cache: a second
command waits for it instead of compiling the same kernels again), takes the lowest priority
(nice 19, SCHED_IDLE on Linux: issue 39, the interpreted tier keeps its core) and compiles the
plan through the warm-up's children (``warmup_child``: each within a memory budget, every
kernel saved to the cache as it compiles; they inherit the priority). Each compile report, then
``{"done": report}`` or ``{"error": message}``, goes to stdout as a JSON line; when the command
that started it has ended (its end of the pipe closed) it goes on quietly, so the next start
finds the kernels compiled.

It runs in a session of its own: Ctrl-C on the terminal reaches the command, which stops it
(SIGTERM to its process group: it and its child end at once, by the signal's default action;
numba writes each cache file beside and renames it into place, and every file is sealed, so
a compile cut anywhere leaves no cache entry that loads half-written).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import pickle
import signal
import sys
import time
from pathlib import Path

LOCK_NAME = "spiel-edge-compile.lock"
LOG_NAME = "spiel-edge-compile.log"
NICE = 19  # the lowest priority: the command's interpreted kernels go first


def lower_priority() -> list[str]:
    """This process (and the children it starts after) at the lowest CPU priority: nice 19,
    and on Linux the SCHED_IDLE class (it runs only when a core has nothing else to run, and
    gives way at once when the command wakes for an acquisition, where nice alone still
    shares a core in slices). What was set, for the log."""
    done = []
    with contextlib.suppress(OSError):
        os.nice(NICE - os.nice(0))
        done.append(f"nice {os.nice(0)}")
    policy = getattr(os, "SCHED_IDLE", None)
    if policy is not None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, policy, os.sched_param(0))
            done.append("SCHED_IDLE")
    return done


def write_plan(path: Path, plan: list[tuple[str, str, tuple]]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(pickle.dumps(plan, protocol=pickle.HIGHEST_PROTOCOL))
    os.replace(tmp, path)


def try_lock(folder: Path):
    """An open, locked file in ``folder`` (held until closed or the process ends), or None
    when another process holds it."""
    folder.mkdir(parents=True, exist_ok=True)
    fh = open(folder / LOCK_NAME, "a+")  # noqa: SIM115 - held past this function
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        return None
    return fh


class _Out:
    """JSON lines to the command while it listens; nothing (and no error) once it is gone."""

    def __init__(self) -> None:
        self.open = True

    def __call__(self, message: dict) -> None:
        if not self.open:
            return
        try:
            sys.stdout.write(json.dumps(message) + "\n")
            sys.stdout.flush()
        except (OSError, ValueError):
            self.open = False


def main(argv: list[str]) -> int:
    from spiel_edge.runtime.warmup import ENV_PLAN, cache_dir
    from spiel_edge.runtime.warmup_child import WarmupError, run_child

    out = _Out()
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):  # the worker stops with us
        signal.signal(sig, _exit_on)
    folder = cache_dir()
    if folder is None:
        out({"error": "no writable folder for compiled kernels"})
        Path(argv[0]).unlink(missing_ok=True)
        return 1
    lock = try_lock(Path(folder))
    if lock is None:
        out({"busy": True})
        Path(argv[0]).unlink(missing_ok=True)
        return 3
    lock.seek(0)
    lock.truncate()
    lock.write(str(os.getpid()))
    lock.flush()
    priority = lower_priority()  # before the worker starts: it inherits both
    os.environ[ENV_PLAN] = os.path.abspath(argv[0])

    print(f"priority: {', '.join(priority) or 'unchanged'}", file=sys.stderr, flush=True)
    t0 = time.monotonic()

    def relay(event: str, name: str, detail: object) -> None:
        out({"event": event, "name": name, "detail": detail})
        if event == "compiled":  # the log keeps each kernel's time (compile_times.json)
            print(
                f"compiled {name} {float(detail):.2f} s (at {time.monotonic() - t0:.0f} s)",
                file=sys.stderr,
                flush=True,
            )

    try:
        report = run_child("plan", relay)
    except WarmupError as exc:
        out({"error": str(exc)})
        return 1
    finally:
        Path(argv[0]).unlink(missing_ok=True)  # the plan was the command's; it may be gone
    out({"done": {"compiled": report["compiled"], "seconds": report["seconds"]}})
    print(
        f"done: {len(report['compiled'])} kernels in {time.monotonic() - t0:.0f} s",
        file=sys.stderr,
        flush=True,
    )
    return 0


def _exit_on(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)  # unwinds through warmup_child, which stops its child


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
