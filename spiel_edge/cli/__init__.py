"""The ``spiel-edge`` command line: thin click commands over the library API.

Each module in this package holds one command (or a group) as a module-level ``command``,
listed in :data:`COMMANDS` with its one-line help: a command's module (and numba, onnxruntime,
...) is imported only when that command runs, so ``--help`` stays fast. One top-level handler
maps SpielError to a one-line message and exit status 2.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import logging
import os
import signal
import sys
import threading
import warnings

import click

from spiel_edge import __version__
from spiel_edge.cli._signals import Terminated, deferred_in_import, interrupted
from spiel_edge.errors import SpielError
from spiel_edge.safety.guard import escape, release_claims, shorten, shorten_tokens

EXIT_OK, EXIT_PARTIAL, EXIT_ERROR = 0, 1, 2

# Signals from the first instruction: the command's own process records INT, TERM and HUP
# from the package's first line (spiel_edge/_early.py); main() turns a recorded one into its
# documented status. Imported as a library (tests, other programs), nothing is installed.
_OWN_PROCESS = "spiel_edge._early" in sys.modules
_CATCH = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def setup_logging(verbosity: int) -> None:
    """Logs go to stderr, one line each, no timestamps when journald adds its own; straight
    into the journal, lines carry a ``<priority>`` prefix so ``journalctl -p`` filters them."""
    from spiel_edge.service.systemd import JournalFormatter, stderr_is_journal

    level = logging.WARNING - 10 * verbosity
    under_journald = "JOURNAL_STREAM" in os.environ or "INVOCATION_ID" in os.environ
    fmt = (
        "%(levelname)s %(name)s: %(message)s"
        if under_journald
        else "%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    logging.basicConfig(level=max(level, logging.DEBUG), format=fmt, stream=sys.stderr, force=True)
    handler = logging.getLogger().handlers[0]
    if stderr_is_journal():
        handler.setFormatter(JournalFormatter())
    handler.addFilter(shorten_record)
    from spiel_edge.runtime.log_limit import ClientLogLimiter  # libraries' client-driven lines

    handler.addFilter(ClientLogLimiter())


def shorten_record(record: logging.LogRecord) -> bool:
    """No log line carries a huge token (a 10 MB argument echoed by some message) nor a raw
    control character (a board's string, a file name, a Zenoh key): a record is one line,
    its newlines shown as ``\\n``, escape sequences as ``\\x1b`` (safety/shown.py)."""
    message = record.getMessage()
    short = shorten_tokens(escape(message))
    if short != message:
        record.msg, record.args = short, None
    return True


# name -> one-line help; the module spiel_edge.cli.<name> holds ``command``. A test checks
# that the help here is the command's own and that every command module is listed.
COMMANDS = {
    "background": "Capture the empty scene for `run --background FILE`.",
    "bench": "Median and p95 microseconds per acquisition (JSON with --json).",
    "calibrate": "Receiver positions, delays, speed of sound from known targets.",
    "config": "Pull, show, diff, push and commit the board's stored config.",
    "doctor": "Check what the service needs; print a fix for each problem.",
    "evaluate": "3-D error, fix rate, association accuracy against ground truth.",
    "firmware": "The board's firmware slots; update with test boot, confirm, rollback.",
    "fuse": "Several boards' targets from Zenoh, fused in the robot's frame.",
    "profile": "Device profiles: geometry, timing and pipeline tuning as TOML.",
    "recover": "Rewrite a damaged or unfinalized recording into a valid one.",
    "replay": "Run the pipeline over recordings; one NDJSON record each.",
    "run": "Stream from the board and write one record per acquisition.",
    "service": "The systemd service kit: unit, user, udev rule, config.",
    "simulate": "The virtual board on a pseudo-terminal (a sim:// URL).",
    "view": "Pictures (PNG): A-scans with echoes and fits, positions and tracks.",
    "warmup": "Compile every kernel into the numba cache this environment uses.",
}


class ReaderGone(Exception):
    """The reader of stdout went away (``| head``): a normal end, status 0."""


SPEAK_WHEN_COLD = ("run", "replay", "evaluate", "calibrate")  # commands that compile kernels


class LazyGroup(click.Group):
    """A group whose subcommands are imported when they run, not when the CLI starts."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        from spiel_edge.cli._types import harden_command

        return harden_command(importlib.import_module(f"{__name__}.{name}").command)

    def resolve_command(self, ctx: click.Context, args: list[str]):
        # a first start says so before the command's module imports numba (about a second)
        if args and args[0] in SPEAK_WHEN_COLD and not {"-h", "--help"} & set(args[1:]):
            from spiel_edge.runtime.cold_start import say_if_cold

            say_if_cold(args[0])
        return super().resolve_command(ctx, args)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except BrokenPipeError as exc:  # click would turn it into a silent exit status 1
            raise ReaderGone from exc

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, COMMANDS[name]) for name in self.list_commands(ctx)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(
    cls=LazyGroup,
    context_settings={"help_option_names": ["-h", "--help"]},
)
@click.version_option(__version__, prog_name="spiel-edge")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
def cli(verbose: int) -> None:
    """3-D ultrasonic echolocation (PaCE) for robots."""
    setup_logging(verbose)


BUG_HINT = (
    "this is a bug in spiel-edge: please report it with the command line and the output of "
    "the same command run with `spiel-edge -vv ...`"
)


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 1 some inputs failed, 2 error).

    No traceback reaches a user: anything unexpected is one line, a bug-report hint and
    status 2 (the traceback only with ``-vv``)."""
    args = sys.argv[1:] if argv is None else list(argv)
    own = _OWN_PROCESS and argv is None
    status = EXIT_ERROR
    try:
        if own:
            _SignalPhase.start()
        _occupy_closed_stdio()
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line  # a library's warning: one line of ours
            status = _main(args)
    except KeyboardInterrupt:  # a signal between the command's end and here
        status = 130
    finally:
        if own:
            _SignalPhase.ending = True  # from here a signal changes nothing: the status stays
        release_claims()
        if args == sys.argv[1:]:  # the process's own command line: it ends now, so skip the
            gc.freeze()  # final GC of numba's and scipy's objects (seconds on a loaded host)
    if own:
        _exit_now(status)
    return status


def _exit_now(status: int) -> None:
    """End the process with ``status`` and nothing else: the interpreter's own finalization
    puts the default handlers back, so a Ctrl-C during it ended the process by the signal
    (status -2) after main had said 130. Every output is closed by its command; the standard
    streams and the log are flushed here."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    with contextlib.suppress(Exception):
        logging.shutdown()
    os._exit(status)


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning from a library (numpy, numba, ...) as one escaped log line, without the
    source line Python would print under it."""
    logging.getLogger("spiel_edge.warnings").warning(
        "%s: %s", category.__name__, shorten(message, 300)
    )


class _SignalPhase:
    """The process's handlers outside a command's own: INT raises KeyboardInterrupt, TERM and
    HUP raise Terminated (both status 130, the finally blocks clean up); once main is
    ending, a signal is ignored so the status it computed is the one the process exits with
    (a second Ctrl-C during shutdown used to kill it by the signal, status -2)."""

    ending = False

    @classmethod
    def start(cls) -> None:
        for sig in _CATCH:
            signal.signal(sig, cls.handler)
        sys.unraisablehook = _quiet_signal_unraisable
        early = sys.modules["spiel_edge._early"].received
        if early:  # a signal arrived while the program was still loading
            cls.handler(early[0], None)

    @classmethod
    def handler(cls, signum: int, frame: object) -> None:
        if cls.ending or deferred_in_import(signum, frame):
            return
        _end_if_stuck()
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise Terminated(f"signal {signum}")


def _quiet_signal_unraisable(unraisable) -> None:
    """A signal's exception raised where Python cannot raise it (a second Ctrl-C while the
    first unwinds, landing in a weakref or finaliser callback inside the import system) is
    printed as "Exception ignored in ..." with a traceback: the process is ending on the
    signal already, so it is dropped (Terminated is a KeyboardInterrupt); anything else goes
    to Python's default hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        return
    sys.__unraisablehook__(unraisable)


STUCK_EXIT_S = 10.0  # after a signal, a clean-up still running this long is stuck
_stuck_timer: list[threading.Timer] = []


def _end_if_stuck() -> None:
    """The signal's exception unwinds the command; should its clean-up block (a lock that a
    library held when the signal came never released), the process still ends, status 130,
    saying so: nothing hangs. Armed once; a daemon thread, so a normal end never waits."""
    if _stuck_timer:
        return

    def force() -> None:
        with contextlib.suppress(OSError):
            os.write(
                2, f"aborted: the clean-up after the signal took over {STUCK_EXIT_S:g} s\n".encode()
            )
        os._exit(130)

    timer = threading.Timer(STUCK_EXIT_S, force)
    timer.daemon = True
    _stuck_timer.append(timer)
    timer.start()


class _ClosedStream:
    """What sys.stdout is when the process was started with stdout closed (``>&-``):
    writing is an error naming it (one line, status 2) instead of a crash."""

    def __init__(self, name: str) -> None:
        self.name = name

    def write(self, text: str) -> int:
        raise OSError(9, f"{self.name} is closed; redirect it (> FILE or > /dev/null)")

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False

    def fileno(self) -> int:
        raise OSError(9, f"{self.name} is closed")


def _occupy_closed_stdio() -> None:
    """A closed standard descriptor is taken by /dev/null, so no file this command opens
    becomes its fd 1 by accident; a closed stdout raises on write, a closed stderr is quiet."""
    for fd, name in ((0, "stdin"), (1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
            continue
        except OSError:
            pass
        try:
            devnull = os.open(os.devnull, os.O_RDWR)
            if devnull != fd:
                os.dup2(devnull, fd)
                os.close(devnull)
        except OSError:
            continue
        if name == "stdout":
            sys.stdout = _ClosedStream("stdout")  # type: ignore[assignment]
        elif name == "stderr":
            sys.stderr = open(os.devnull, "w")  # noqa: SIM115
    if sys.stdout is None:
        sys.stdout = _ClosedStream("stdout")  # type: ignore[assignment]
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115


def _main(args: list[str]) -> int:
    try:
        result = cli.main(args=args, prog_name="spiel-edge", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        return 130
    except click.ClickException as exc:
        _show_click(exc)
        return EXIT_ERROR if exc.exit_code == 1 else exc.exit_code
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except SpielError as exc:
        if interrupted(exc):
            return 130
        _error(f"error: {exc}", args, exc)
        return EXIT_ERROR
    except KeyboardInterrupt:
        return 130
    except (BrokenPipeError, ReaderGone):  # the reader of stdout went away (| head)
        _silence_stdout()
        return EXIT_OK
    except OSError as exc:  # a disk that filled up, a folder that went away, ...
        if interrupted(exc):
            return 130
        where = f": {shorten(exc.filename)}" if getattr(exc, "filename", None) else ""
        _error(f"error: {exc.strerror or exc}{where}", args, exc)
        return EXIT_ERROR
    except MemoryError as exc:
        _error("error: out of memory (an input too large for this machine?)", args, exc)
        return EXIT_ERROR
    except Exception as exc:  # the last resort: a bug, or a library's error we know
        if interrupted(exc):  # a library turned the signal's interrupt into its own error
            return 130
        known = _library_error(exc)
        if known:
            _error(f"error: {known}", args, exc)
            return EXIT_ERROR
        _error(f"internal error: {type(exc).__name__}: {shorten(exc, 200)}", args, exc)
        click.echo(BUG_HINT, err=True)
        return EXIT_ERROR
    return _status(result)


def _library_error(exc: Exception) -> str | None:
    """A library's error we can name in our own words (one line with a fix), else None."""
    text = str(exc)
    if isinstance(exc, RuntimeError) and "no locator available" in text:
        return (
            "numba cannot write its cache beside spiel-edge nor in NUMBA_CACHE_DIR; set "
            "NUMBA_CACHE_DIR to a folder you can write (e.g. ~/.cache/spiel-edge/numba)"
        )
    if isinstance(exc, RecursionError):
        return "an input is nested too deeply to read"
    return None


def _status(result: object) -> int:
    return result if isinstance(result, int) and 0 <= result <= 255 else EXIT_OK


def _show_click(exc: click.ClickException) -> None:
    import io

    buffer = io.StringIO()
    exc.show(file=buffer)
    with contextlib.suppress(OSError, ValueError):  # stderr itself may be gone
        click.echo(shorten_tokens(buffer.getvalue()), err=True, nl=False)


def _error(line: str, args: list[str], exc: BaseException) -> None:
    try:
        click.echo(shorten_tokens(escape(line)), err=True)
        if _verbosity(args) >= 2:
            import traceback

            traceback.print_exception(exc, file=sys.stderr)
    except (OSError, ValueError):  # stderr itself is gone: nothing more can be said
        pass


def _verbosity(args: list[str]) -> int:
    """-v/-vv/--verbose given before the command (counted here: the group may not have run)."""
    count = 0
    for arg in args:
        if arg == "--verbose":
            count += 1
        elif arg.startswith("-") and not arg.startswith("--") and set(arg[1:]) == {"v"}:
            count += len(arg) - 1
        elif not arg.startswith("-"):
            break
    return count


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's last flush does not fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass
