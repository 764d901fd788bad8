"""``spiel-edge replay``: recorded acquisitions through the live pipeline, NDJSON out."""

from __future__ import annotations

import click

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._options import (
    association_option,
    calibration_option,
    max_targets_option,
    profile_option,
)
from spiel_edge.outputs.ndjson import NdjsonSink
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import resolve_profile
from spiel_edge.runtime.replay import FORMATS, iter_sources, replay


@click.command("replay")
@click.argument("path", type=click.Path(exists=True))
@click.option(
    "--format",
    "fmt",
    type=click.Choice(FORMATS),
    default=None,
    help="Recording format (default: mcap for *.mcap, else spiel-csv).",
)
@click.option(
    "--background",
    type=click.Path(exists=True, file_okay=False),
    default=None,
    help="Folder of same-named target-free frames (spiel-csv).",
)
@profile_option
@calibration_option
@association_option
@max_targets_option
@click.option(
    "--output", "-o", default="-", show_default=True, help="NDJSON file, or - for stdout."
)
def command(
    path, fmt, background, profile_name, calibration, association, max_targets, output
) -> int:
    """Run the pipeline over recorded frames; one NDJSON record per acquisition.

    Label files are never read. Exit status 1 when some inputs could not be processed.
    """
    pipeline = build_pipeline(resolve_profile(profile_name, calibration), association)
    if max_targets:
        pipeline.set_max_targets(max_targets)
    failed = total = 0
    sink = NdjsonSink(output)
    try:
        for item in replay(pipeline, iter_sources(path, fmt, background)):
            sink.write(item.record())
            total += 1
            failed += item.error is not None
    finally:
        sink.close()
    if failed:
        click.echo(f"{failed} of {total} acquisitions could not be processed", err=True)
    return EXIT_PARTIAL if failed else EXIT_OK
