"""``spiel-edge recover``: a damaged, cut or unfinalized recording rewritten into a valid one."""

from __future__ import annotations

import click

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._options import force_option
from spiel_edge.safety.guard import FilePlan
from spiel_edge.safety.shown import escape


@click.command("recover")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option(
    "--output", "-o", required=True, type=click.Path(dir_okay=False), help="The new FILE.mcap."
)
@force_option
def command(file: str, output: str, force: bool) -> int:
    """Rewrite a damaged or unfinalized MCAP recording FILE into a valid one.

    Every readable message is kept with its sequence number and times; damaged chunks are
    skipped and summarized. FILE is never modified. Exit status 1 when something was lost.
    """
    from spiel_edge.recordings.recover import recover

    plan = FilePlan(force)
    plan.input_file(file, "FILE")
    plan.output(output, "--output")
    result = recover(file, output)
    click.echo(f"{escape(output)}: {result.summary()}", err=True)
    return EXIT_PARTIAL if result.lost_data else EXIT_OK
