"""A tiered start: the first record at once on the interpreted kernels, the compiled ones when
a background process has compiled them (issue 39; docs/first-start.md).

:func:`start_tiered`, before a command opens its board:

1. tries the command's kernels with compiling forbidden (``_kernel_cache.no_compile``); all
   cached: the compiled tier, nothing else happens;
2. else puts the interpreted tier in place (``spiel_edge._tiers``) and runs what the command
   will run on a closed-form acquisition of its profile (``first_start.exercise_run``),
   noting each call from Python into a kernel with its argument types: the compile plan,
   only what this configuration needs;
3. starts ``tier_compile`` on that plan in a background process (low priority, one per
   cache folder) and returns at once.

The live loop calls :meth:`TieredStart.between` between two acquisitions; once the
background compile has ended, a thread here loads the planned kernels from the cache
(forbidden to compile: a missing one goes to another round), and the next ``between`` puts
the dispatchers back: the pipeline, tracker, session and outputs are the same objects on
both tiers, and the records are the same (tests/core/test_tiered.py).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)

ENV_TIERED = "SPIEL_EDGE_TIERED"  # "0": compile before the first record (the old way)
ENV_AFTER = "SPIEL_EDGE_COMPILE_AFTER_EXIT"  # "0": stop the compile when the command ends
MAX_ROUNDS = 3  # compile rounds (a later one for calls first seen on the live stream)
POLL_S = 0.05  # switch_at_kernel_calls: the switch looked at at most this often
REPORT_EVERY = 0.25  # without a status line: a progress line every quarter of the kernels


class TieredStart:
    """The tier a command runs on, and the background compile that ends it."""

    def __init__(self, stream=None, notifier=None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.notifier = notifier
        self.interpreted = None  # spiel_edge._tiers.Interpreted while it runs
        self.tier = "compiled"
        self.total = 0  # kernels the plan compiles
        self.estimate_s = 0.0
        self.done: set[str] = set()
        self.planned: set[str] = set()
        self.compile_s: dict[str, float] = {}
        self.t0 = time.monotonic()
        self.switched_after: float | None = None
        self.records_interpreted = 0
        self.proc: subprocess.Popen | None = None
        self.error: str | None = None
        self.rounds = 0
        self._plan_file: Path | None = None
        self._ready = threading.Event()
        self._loader: threading.Thread | None = None
        self._said = 0.0
        self._waiting_on_other = False
        self.stopped = False  # the command stopped the compile (close)
        self._polled = 0.0  # switch_at_kernel_calls: when the switch was last looked at

    # --- the two tiers -------------------------------------------------------------------

    @property
    def is_interpreted(self) -> bool:
        return self.tier == "interpreted"

    def between(self) -> bool:
        """Between two acquisitions: switch to the compiled kernels when they are loaded.
        True when it switched now."""
        if self.tier != "interpreted":
            return False
        self.records_interpreted += 1
        return self._switch_if_ready()

    def leave(self) -> None:
        """The command is over: the dispatchers back where the twins were (for a command
        run in-process; the records are written by then)."""
        if self.interpreted is not None:
            self.interpreted.on_call = None
            self.interpreted.leave()

    def switch_at_kernel_calls(self) -> None:
        """For a command whose loops are not its own (evaluate, calibrate): the switch comes
        at the next call from Python into a kernel once the compiled ones are loaded (between
        two kernel calls: the values are the same on both tiers, so a unit of work may end on
        the compiled tier)."""
        if self.interpreted is not None and self.tier == "interpreted":
            self.interpreted.on_call = self._at_kernel_call

    def _at_kernel_call(self) -> bool:
        if self.tier != "interpreted":
            return True
        now = time.monotonic()
        if now - self._polled < POLL_S:  # a flag and a clock per kernel call, no more
            return False
        self._polled = now
        return self._switch_if_ready()

    def _switch_if_ready(self) -> bool:
        if self._waiting_on_other and self.proc is None:
            self._poll_other()
        if not self._ready.is_set():
            return False
        self.interpreted.on_call = None
        self.interpreted.leave()
        self.tier = "compiled"
        self.switched_after = time.monotonic() - self.t0
        on = (
            f"{self.records_interpreted} records on the interpreted ones"
            if self.records_interpreted
            else "the work so far on the interpreted ones"
        )
        line = f"spiel-edge: compiled kernels in use after {self.switched_after:.0f} s ({on})"
        self._say(line)
        if self.notifier is not None:
            self.notifier.status(line)
        return True

    # --- progress ------------------------------------------------------------------------

    def progress(self) -> dict:
        left = max(self.estimate_s - sum(self.compile_s.values()), 0.0)
        return {
            "tier": self.tier,
            "compiled": len(self.done & self.planned),
            "to_compile": self.total,
            "estimate_left_s": round(left),
            "switched_after_s": None
            if self.switched_after is None
            else round(self.switched_after, 1),
            "error": self.error,
        }

    def status_text(self) -> str:
        if self.tier == "compiled":
            return "kernels compiled"
        if self.stopped:
            p = self.progress()
            return f"kernels interpreted (compile stopped at {p['compiled']}/{p['to_compile']})"
        if self.error:
            return f"kernels interpreted (compile failed: {self.error})"
        if self._waiting_on_other:
            return "kernels interpreted, another process compiles them"
        p = self.progress()
        if self._ready.is_set() or p["compiled"] >= p["to_compile"]:
            return "kernels interpreted, loading the compiled ones"
        return (
            f"kernels interpreted, compiling {p['compiled']}/{p['to_compile']} "
            f"(~{p['estimate_left_s']} s left)"
        )

    def _say(self, line: str) -> None:
        try:
            self.stream.write("\r\x1b[K" * _isatty(self.stream) + line + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            pass

    # --- the background compile ----------------------------------------------------------

    def launch(self, plan: list[tuple], folder: str) -> None:
        """Start compiling ``plan`` ([(module, attribute, types)]) in the background."""
        from spiel_edge.runtime.tier_compile import LOG_NAME, write_plan

        self.rounds += 1
        fd, name = tempfile.mkstemp(prefix="spiel-edge-plan-", suffix=".pickle")
        os.close(fd)
        self._plan_file = Path(name)
        write_plan(self._plan_file, plan)
        log_path = Path(folder) / LOG_NAME
        try:
            err = open(log_path, "ab")  # noqa: SIM115 - the child's; closed below
        except OSError:
            err = subprocess.DEVNULL
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "spiel_edge.runtime.tier_compile", str(self._plan_file)],
            stdout=subprocess.PIPE,
            stderr=err,
            stdin=subprocess.DEVNULL,
            text=True,
            start_new_session=True,  # Ctrl-C reaches the command, which stops it (close)
        )
        if err is not subprocess.DEVNULL:
            err.close()
        threading.Thread(target=self._listen, args=(self.proc,), daemon=True).start()

    def _listen(self, proc: subprocess.Popen) -> None:
        busy = False
        for line in proc.stdout:
            try:
                message = json.loads(line)
            except ValueError:
                continue
            if "event" in message:
                self._on_event(message["event"], message["name"], message["detail"])
            elif "error" in message:
                self.error = message["error"]
            elif "busy" in message:
                busy = True
        status = proc.wait()
        self.proc = None
        if self.stopped:  # by close(): said there
            return
        if busy:  # another command compiles into this cache: wait for it, then load
            self._waiting_on_other = True
            return
        if status == 0 and self.error is None:
            self._load()
        elif self.error is None:
            self.error = f"the compile process ended with status {status}"
        if self.error:
            self._say(f"spiel-edge: {self.error}: staying on the interpreted kernels")

    def _on_event(self, event: str, name: str, detail) -> None:
        if event == "compiled":
            self.compile_s[name] = self.compile_s.get(name, 0.0) + float(detail)
            new = name not in self.done
            self.done.add(name)
            if name not in self.planned:  # more than planned: counted, honestly
                self.planned.add(name)
                self.total += 1
            if new:
                self._report()

    def _report(self) -> None:
        p = self.progress()
        if self.notifier is not None:
            self.notifier.status(self.status_text())
        if _isatty(self.stream):
            return  # the status line shows it
        share = p["compiled"] / max(p["to_compile"], 1)
        if share - self._said >= REPORT_EVERY or p["compiled"] == p["to_compile"]:
            self._said = share
            self._say(
                f"spiel-edge: compiled {p['compiled']}/{p['to_compile']} kernels "
                f"({time.monotonic() - self.t0:.0f} s; interpreted meanwhile)"
            )

    def _poll_other(self) -> None:
        from spiel_edge.runtime.tier_compile import try_lock

        lock = try_lock(Path(self._folder))
        if lock is not None:
            lock.close()
            self._waiting_on_other = False
            threading.Thread(target=self._load, daemon=True).start()

    def _load(self) -> None:
        """Load every planned call's compiled kernel (never compiling here); ready when all
        loaded, else another round for the missing ones."""
        from spiel_edge import _kernel_cache
        from spiel_edge._tiers import where

        missing = []
        with _kernel_cache.no_compile():
            for dispatcher, argtypes in self.interpreted.calls:
                try:
                    dispatcher.compile(argtypes)
                except _kernel_cache.CompileNeeded:
                    missing.append((dispatcher, argtypes))
                except Exception as exc:  # a call numba cannot compile: the record says it
                    log.debug("%s%s: %s", dispatcher, argtypes, exc)
        if not missing:
            self._ready.set()
        elif self.rounds < MAX_ROUNDS:
            self.launch([(*where(k), t) for k, t in missing], self._folder)
        else:
            self.error = f"{len(missing)} kernels not compiled after {self.rounds} rounds"

    def close(self, stop_compile: bool) -> str | None:
        """The command ends: stop the compile (``stop_compile``, or SPIEL_EDGE_COMPILE_AFTER_EXIT
        =0), else leave it running; the line saying which, or None when none runs. A stopped
        compile's line is said here, before waiting for the compile to end (None returned):
        run from the signal watchdog's thread, the command may exit during that wait."""
        proc = self.proc  # (its plan file is the compile process's to remove)
        if proc is None or proc.poll() is not None:
            return None
        if stop_compile or os.environ.get(ENV_AFTER, "1") == "0":
            self.stopped = True
            p = self.progress()
            with contextlib.suppress(OSError):
                os.killpg(proc.pid, signal.SIGTERM)
            self._say(
                f"spiel-edge: compile stopped at {p['compiled']}/{p['to_compile']} kernels "
                "(kept in the cache; the next start goes on from there)"
            )
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=10)  # at the lowest priority it may need a moment
            if self._plan_file is not None:  # stopped before it could remove it
                self._plan_file.unlink(missing_ok=True)
            return None
        p = self.progress()
        return (
            f"spiel-edge: kernels keep compiling in the background (pid {proc.pid}, "
            f"{p['compiled']}/{p['to_compile']} done, ~{p['estimate_left_s']} s left): "
            "later starts use them"
        )


def _isatty(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def enabled() -> bool:
    return os.environ.get(ENV_TIERED, "1") != "0"  # "force": tiered even when all is cached


def start_tiered(
    profile,
    association=None,
    max_targets=None,
    track=True,
    toa_correction=None,
    stream=None,
    notifier=None,
    what: str = "run",
    exercise=None,
    pipeline=None,
) -> TieredStart | None:
    """Before a command opens its board: the compiled tier when every kernel it needs is
    cached; else the interpreted tier with its compile started in the background. None when
    a tiered start is off or impossible (SPIEL_EDGE_TIERED=0, no writable cache folder,
    numba outside the tested range): then kernels compile first, as before. ``pipeline``:
    the command's own for ``profile``, exercised in place of a second one (runtime/live.py)."""
    from spiel_edge import _kernel_cache, _tiers
    from spiel_edge.errors import SpielError
    from spiel_edge.runtime.first_start import (
        cache_writable,
        exercise_run,
        make_plan,
        prepare_for_run,
    )
    from spiel_edge.runtime.warmup import cache_dir

    tiers = TieredStart(stream, notifier)
    first = "(SPIEL_EDGE_TIERED=force)"
    try:
        if os.environ.get(ENV_TIERED) != "force":  # force: tests, bench (as if none cached)
            with _kernel_cache.no_compile():
                if exercise is not None:  # a command of its own kernels (fuse: the tracker)
                    exercise()
                else:
                    exercise_run(profile, association, max_targets, track, toa_correction, pipeline)
            return tiers  # all cached: the compiled tier
    except _kernel_cache.CompileNeeded as exc:
        if os.environ.get(_kernel_cache.ENV_FORBID, "0") not in ("", "0"):
            raise  # SPIEL_EDGE_NO_COMPILE=1: a missing kernel is an error
        first = exc.name
    except SpielError as exc:  # an unusual profile: the live stream will tell
        log.debug("kernel preparation: %s", exc)
        return tiers
    folder = cache_dir()
    if not enabled() or not cache_writable() or folder is None or not _tiers.KERNELS:
        if exercise is None:  # (a command of its own kernels compiles them in place)
            prepare_for_run(
                profile,
                association,
                max_targets,
                track,
                toa_correction,
                stream,
                notifier,
                pipeline,
            )
        return None
    interpreted, plan, units = make_plan(
        profile, association, max_targets, track, toa_correction, exercise
    )
    tiers.interpreted, tiers.tier, tiers._folder = interpreted, "interpreted", folder
    tiers.planned = set(units)
    tiers.total = len(tiers.planned)
    from spiel_edge.runtime.compile_progress import about, estimate_for

    tiers.estimate_s = estimate_for(sorted(tiers.planned))
    doing = (
        f"compiles the {tiers.total} kernels this command needs ({about(tiers.estimate_s)})"
        if tiers.total
        else "loads the compiled kernels"
    )
    tiers._say(
        f"spiel-edge {what}: kernel {first} has no compiled copy: starting on the interpreted "
        f"kernels (slower, the same records) while a background process {doing}; "
        f"log: {Path(folder) / 'spiel-edge-compile.log'}"
    )
    if notifier is not None:
        notifier.status("interpreted kernels; compiling in the background")
    try:
        tiers.launch(plan, folder)
    except BaseException:  # a signal right then: no compile left behind in its own session
        tiers.close(stop_compile=True)
        raise
    return tiers


@contextlib.contextmanager
def tiered_work(
    profile,
    association=None,
    max_targets=None,
    track=True,
    toa_correction=None,
    what: str = "evaluate",
    exercise=None,
    stopped=None,
):
    """A tiered start for a command whose loops are not its own (``evaluate``, ``calibrate``):
    within, missing kernels run interpreted while they compile in the background, and the
    switch comes at a kernel call once they are loaded (:meth:`TieredStart.
    switch_at_kernel_calls`). Yields the :class:`TieredStart` (None when off: kernels compile
    first, as before). A normal end leaves the compile running (later starts use it); an
    exception or a signal stops it (``stopped()`` true: a command that stops on a signal
    without an exception); either way one line says so. ``exercise``: the plan's work when it
    is not ``run``'s (``fuse``: the tracker alone)."""
    if profile is None and exercise is None:  # nothing of run's and none of its own
        yield None
        return
    tiers = start_tiered(
        profile, association, max_targets, track, toa_correction, what=what, exercise=exercise
    )
    if tiers is not None:
        tiers.switch_at_kernel_calls()
    stop = True
    try:
        yield tiers
        stop = bool(stopped is not None and stopped())
    finally:
        if tiers is not None:
            tiers.leave()  # the dispatchers back (a command run in-process)
            line = tiers.close(stop_compile=stop)
            if line:
                tiers._say(line)
