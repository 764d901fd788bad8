"""The ``spiel-edge`` command line: thin click commands over the library API.

Each module in this package holds one command (or a group) as a module-level ``command``;
they are discovered here, so adding a command never touches this file. One top-level handler
maps SpielError to a one-line message and exit status 2.
"""

from __future__ import annotations

import importlib
import logging
import os
import pkgutil
import sys

import click

from spiel_edge import __version__
from spiel_edge.errors import SpielError

EXIT_OK, EXIT_PARTIAL, EXIT_ERROR = 0, 1, 2


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
    if stderr_is_journal():
        logging.getLogger().handlers[0].setFormatter(JournalFormatter())


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="spiel-edge")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
def cli(verbose: int) -> None:
    """3-D ultrasonic echolocation (PaCE) for robots."""
    setup_logging(verbose)


def _register_commands() -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        command = getattr(module, "command", None)
        if command is not None:
            cli.add_command(command)


_register_commands()


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 1 some inputs failed, 2 error)."""
    try:
        result = cli.main(args=argv, prog_name="spiel-edge", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        return 130
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except SpielError as exc:
        click.echo(f"error: {exc}", err=True)
        return EXIT_ERROR
    except KeyboardInterrupt:
        return 130
    return int(result or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
