"""``spiel-edge calibrate``: receiver positions, delays and speed of sound from known targets."""

from __future__ import annotations

import sys

import click
import numpy as np

from spiel_edge.calibrate import (
    FIXABLE,
    calibrate_echoes,
    extract_echoes,
    load_recordings,
    read_positions,
)
from spiel_edge.calibrate.report import (
    calibration_toml,
    plot_calibration,
    report_text,
    summary_lines,
)
from spiel_edge.calibrate.validate import cross_validate
from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._options import (
    association_option,
    board_port,
    calibration_option,
    port_option,
    profile_option,
    toa_correction_option,
)
from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.errors import ConfigError
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import resolve_profile
from spiel_edge.runtime.tiered import tiered_work
from spiel_edge.safety.guard import FilePlan, atomic_write
from spiel_edge.safety.shown import escape
from spiel_edge.view import require_matplotlib


@click.command("calibrate")
@click.option(
    "--recordings",
    type=click.Path(exists=True),
    default=None,
    help="Offline: a folder of labelled spiel-csv recordings (target positions from the label "
    "files), or a labelled .npz such as spiel_edge/data/spiel_icra23_subset.npz.",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["spiel-csv"]),
    default="spiel-csv",
    show_default=True,
    help="Format of --recordings (kept for scripts: the content decides, folder or .npz).",
)
@click.option(
    "--background",
    type=click.Path(exists=True, file_okay=False),
    default=None,
    help="Folder of same-named target-free frames.",
)
@click.option(
    "--exclude-z",
    type=float,
    multiple=True,
    help="Skip recordings whose target is at this height (mm); repeatable (default: the "
    "mislabelled z = 90 mm of spiel-icra23, as evaluate).",
)
@port_option
@click.option(
    "--positions",
    type=click.Path(exists=True, dir_okay=False),
    default=None,
    help="Live: CSV of target positions x, y, z in mm, one per row.",
)
@click.option(
    "--captures",
    type=click.IntRange(1, 10000),
    default=10,
    show_default=True,
    help="Live: acquisitions per position.",
)
@click.option(
    "--no-prompt", is_flag=True, help="Live: do not wait for Enter (a robot moves the target)."
)
@profile_option
@calibration_option
@click.option(
    "--fix",
    "fix",
    type=click.Choice(FIXABLE),
    multiple=True,
    help="Keep these at the profile's values (repeatable); by default all are estimated.",
)
@click.option(
    "--reject-sigma",
    type=click.FloatRange(2.0, 20.0),
    default=4.0,
    show_default=True,
    help="Echo times further than this many robust scales from the fit are rejected.",
)
@click.option(
    "--output",
    "-o",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the calibration TOML here (accepted by --calibration and `config push`).",
)
@click.option(
    "--plot",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write a PNG of the geometry and the residuals (needs the 'plot' extra).",
)
@click.option(
    "--report",
    "report_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also write the short report (before/after on unseen positions, the decision) here.",
)
@association_option
@toa_correction_option
@click.option(
    "--force",
    is_flag=True,
    help="Overwrite existing output files, and write the calibration even when it is worse "
    "than the start on positions it did not fit.",
)
def command(
    recordings,
    fmt,
    background,
    exclude_z,
    port,
    positions,
    captures,
    no_prompt,
    profile_name,
    calibration,
    fix,
    reject_sigma,
    output,
    plot,
    report_path,
    association,
    toa_correction,
    force,
) -> int:
    """Estimate receiver positions (and the emitter's), per-channel delays and the speed of sound
    from a target at known positions: offline from labelled recordings, or live, guided.

    Before writing, the calibration is checked on positions it did not fit: the data is split
    by (x, y) position into folds, each fold solved from the others and located with the
    pipeline, before and after. A calibration that makes those positions worse is not written
    (exit status 1; --force writes it). docs/calibration.md.
    """
    plan = FilePlan(force)  # outputs checked before anything is captured or fitted
    for path, option in ((calibration, "--calibration"), (positions, "--positions")):
        if path:
            plan.input_file(path, option)
    plan.input_if_file(profile_name, "--profile")
    plan.output(output, "--output")
    plan.output(plot, "--plot")
    plan.output(report_path, "--report")
    if plot:  # before anything is captured, fitted or written
        require_matplotlib("--plot")
    profile = resolve_profile(profile_name, calibration)
    if (recordings is None) == (positions is None):
        raise ConfigError(
            "give either --recordings DIR (offline) or --positions FILE (live, on --port or "
            "the one attached board)"
        )
    # missing kernels: the interpreted ones run (and a live capture goes on) while a
    # background process compiles them; the compiled ones from a kernel call once loaded
    with tiered_work(profile, association, None, False, toa_correction, "calibrate"):
        if recordings is not None:
            data = load_recordings(recordings, background, exclude_z=exclude_z or EXCLUDED_Z_MM)
            frames, backgrounds, truth, source = (
                data.frames,
                data.backgrounds,
                data.truth_mm,
                recordings,
            )
        else:
            port = board_port(port)
            frames, backgrounds, truth = _capture_live(
                port, profile, read_positions(positions), captures, not no_prompt
            )
            source = port
            from spiel_edge.runtime.loop import live_toa_correction  # the pipeline `run` builds

            toa_correction = live_toa_correction(port, toa_correction)
        candidates = extract_echoes(profile, frames, backgrounds)

        def solve_on(mask):
            return calibrate_echoes(
                candidates[mask], truth[mask], profile, fix=set(fix), reject_sigma=reject_sigma
            )

        cal = solve_on(np.ones(len(truth), dtype=bool))
        for line in summary_lines(cal):
            click.echo(line, err=True)
        validation = cross_validate(
            profile,
            cal.geometry,
            frames,
            backgrounds,
            truth,
            solve=lambda mask: solve_on(mask).geometry,
            build=lambda p: build_pipeline(p, association, toa_correction),
        )
        refused = validation.worse and not force and output is not None
        report = report_text(cal, validation, str(source), output, refused)
        click.echo(report, err=True, nl=False)
        if report_path:
            with atomic_write(report_path) as fh:
                fh.write(report)
        if output and not refused:
            with atomic_write(output) as fh:
                fh.write(calibration_toml(cal, str(source), validation))
            click.echo(f"calibration written to {escape(output)}", err=True)
        if plot:
            plot_calibration(cal, plot, validation)
            click.echo(f"plot written to {escape(plot)}", err=True)
        return EXIT_PARTIAL if refused else EXIT_OK


def open_session(port: str):
    """The board session (imported here: offline calibration needs no device stack)."""
    from spiel_edge.device import DeviceSession

    session = DeviceSession(port, reconnect=False)
    session.open()
    return session


def _wait_for_enter(message: str) -> None:
    """The operator's Enter; stdin at its end (closed, a script that ran out of lines) is an
    error saying what to do, not an interruption (Ctrl-C stays one: status 130)."""
    click.echo(message + ": ", err=True, nl=False)
    line = sys.stdin.readline() if sys.stdin is not None else ""
    if not line:
        click.echo("", err=True)
        raise ConfigError(
            "stdin ended before every position was confirmed; nothing was written "
            "(use --no-prompt when a robot moves the target)"
        )


def _capture_live(port: str, profile, positions, captures: int, prompt: bool):
    from spiel_edge.calibrate.capture import capture_positions

    def before_position(i: int, p) -> None:
        if i < 0:
            where = "Clear the scene (no target) for the background capture"
        else:
            where = f"Place the target at position {i + 1}/{len(positions)}: x={p[0]:g} y={p[1]:g} z={p[2]:g} mm"
        if prompt:
            _wait_for_enter(where + ", then press Enter")
        else:
            click.echo(where, err=True)

    session = open_session(port)
    try:
        with click.progressbar(
            length=len(positions) * captures, label="capturing", file=sys.stderr
        ) as bar:
            return capture_positions(
                session,
                profile,
                positions,
                captures=captures,
                before_position=before_position,
                progress=bar.update,
            )
    finally:
        session.close()
