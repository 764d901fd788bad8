"""``spiel-edge view``: pictures (PNG) of A-scans and of positions and tracks (the 'plot' extra)."""

from __future__ import annotations

from pathlib import Path

import click

from spiel_edge.cli import EXIT_OK
from spiel_edge.cli._options import (
    association_option,
    calibration_option,
    force_option,
    profile_option,
    toa_correction_option,
)
from spiel_edge.errors import InputError
from spiel_edge.safety.guard import FilePlan


@click.group("view")
def command() -> None:
    """Pictures as PNG (needs the 'plot' extra: pip install 'spiel-edge[plot]'): `ascan` for
    the A-scans of a recorded acquisition with its echoes and MEMG fits, `positions` for the
    targets and tracks of run or replay records. `calibrate --plot` and `evaluate --plot` draw
    the calibration before/after and the error by position."""


@command.command("ascan")
@click.argument("path", type=click.Path(exists=True))
@click.option(
    "--index",
    type=click.IntRange(0),
    default=0,
    show_default=True,
    help="Which acquisition of the recording (0 is the first).",
)
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False),
    default="ascan.png",
    show_default=True,
    help="The PNG to write.",
)
@profile_option
@calibration_option
@association_option
@toa_correction_option
@force_option
def ascan_cmd(path, index, output, profile_name, calibration, association, toa_correction, force):
    """The A-scans of one acquisition of PATH (a spiel-csv folder, an MCAP recording or a
    labelled .npz such as spiel_edge/data/spiel_icra23_subset.npz): each channel's envelope
    after background subtraction, the detected echoes (red; the matched one green) and the
    fitted MEMG components (blue)."""
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import resolve_profile
    from spiel_edge.runtime.recorded import format_of, iter_sources
    from spiel_edge.safety.limits import InputLimits
    from spiel_edge.view import require_matplotlib
    from spiel_edge.view.ascan import draw_ascan

    require_matplotlib("view")
    plan = FilePlan(force)
    plan.input_any(path, "PATH")
    plan.output(output, "--output")
    fmt = format_of(Path(path))
    profile = resolve_profile(profile_name, calibration)
    pipeline = build_pipeline(profile, association, toa_correction, fused=False)
    seen = 0
    for rec in iter_sources(path, fmt, None, InputLimits.for_profile(profile)):
        if seen < index:
            seen += 1
            continue
        if rec.error is not None:
            raise InputError(rec.error)
        drawn = draw_ascan(pipeline, rec.frames, rec.background, output, title=rec.source)
        echoes = sum(len(e) for e in drawn["echoes"])
        click.echo(
            f"{output}: {rec.source}, {echoes} echoes on {len(drawn['echoes'])} channels",
            err=True,
        )
        return EXIT_OK
    raise InputError(f"{path}: has no acquisition {index} (it holds {seen})")


@command.command("positions")
@click.argument("records", type=click.Path(exists=True, dir_okay=False))
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False),
    default="positions.png",
    show_default=True,
    help="The PNG to write.",
)
@force_option
def positions_cmd(records, output, force):
    """Targets and tracks of RECORDS (NDJSON from run, replay or fuse): a top view (x, y) and
    a side view (x, z) with each target's 95 % ellipse (the last 200), the tracks as lines and
    the ground truth (truth_mm) where the records carry it."""
    from spiel_edge.view import require_matplotlib
    from spiel_edge.view.positions import draw_positions, read_records

    require_matplotlib("view")
    plan = FilePlan(force)
    plan.input_file(records, "RECORDS")
    plan.output(output, "--output")
    drawn = draw_positions(read_records(records), output, title=Path(records).name)
    click.echo(
        f"{output}: {drawn['targets']} targets, {drawn['ellipses']} ellipses, "
        f"{drawn['tracks']} tracks",
        err=True,
    )
    return EXIT_OK
