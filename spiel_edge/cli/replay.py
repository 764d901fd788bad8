"""``spiel-edge replay``: recorded acquisitions through the live pipeline, NDJSON out."""

from __future__ import annotations

import contextlib
import threading
from contextlib import closing
from pathlib import Path

import click

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._options import (
    association_option,
    calibration_option,
    force_option,
    jobs_option,
    max_targets_option,
    profile_option,
    toa_correction_option,
)
from spiel_edge.cli._recording_profile import recording_profile
from spiel_edge.cli._ros2 import ros2_record_options, ros2_settings
from spiel_edge.cli._signals import Finalizers, stop_on_signals
from spiel_edge.errors import ConfigError, OutputError
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.recordings.spiel_csv import frame_files
from spiel_edge.runtime.parallel import PipelineRecipe, replay_files, usable_jobs
from spiel_edge.runtime.recorded import (
    FORMATS,
    ReplaySummary,
    chosen_toa_correction,
    format_of,
    iter_sources,
    recorded_toa_correction,
    replay,
)
from spiel_edge.runtime.recorded_output import is_mcap_output, open_replay_output
from spiel_edge.runtime.tiered import start_tiered
from spiel_edge.runtime.track_records import replay_tracked
from spiel_edge.safety.guard import FilePlan
from spiel_edge.safety.limits import InputLimits


@click.command("replay")
@click.argument("path", type=click.Path(exists=True))
@click.option(
    "--format",
    "fmt",
    type=click.Choice(FORMATS),
    default=None,
    help="Recording format (default: mcap for *.mcap, stof-chirp for a folder of "
    "NN_envelope_frame.txt, else spiel-csv).",
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
@toa_correction_option
@click.option(
    "--output",
    "-o",
    default="-",
    show_default=True,
    help="NDJSON file, - for stdout, or FILE.mcap: a recording as `run --record` writes it.",
)
@ros2_record_options
@force_option
@click.option(
    "--track",
    is_flag=True,
    help="Track targets over the recordings in time order; records gain `tracks` "
    "(docs/tracking.md).",
)
@jobs_option
def command(
    path,
    fmt,
    background,
    profile_name,
    calibration,
    association,
    max_targets,
    toa_correction,
    output,
    force,
    track,
    jobs,
    **ros2,
) -> int:
    """Run the pipeline over recorded frames; one record per acquisition (NDJSON, or an MCAP
    recording that replays again, JSON or --record-profile ros2: docs/ros2.md).

    PATH is a spiel-csv folder, an MCAP recording or a labelled .npz (the vendored
    spiel_edge/data/spiel_icra23_subset.npz), told by its content. Label files of a spiel-csv
    folder are never read; a recording that carries the ground truth (a labelled .npz, a
    `run --record` of the virtual board) keeps it in each record as `truth_mm`. A summary
    line goes to stderr at the end. Exit status 1 when some inputs could not be processed. An
    output file appears only complete (written beside it, then renamed into place).
    """
    plan = FilePlan(force)
    plan.input_any(path, "PATH")
    if background:
        plan.input_folder(background, "--background")
    if calibration:
        plan.input_file(calibration, "--calibration")
    plan.input_if_file(profile_name, "--profile")
    plan.output(output, "--output")
    fmt = format_of(Path(path), fmt)  # by content: one line for what is not a recording
    if background and fmt != "spiel-csv":
        raise ConfigError(f"--background is for a spiel-csv folder; {path} is {fmt}")
    profile = recording_profile(path, fmt, profile_name, calibration)
    frame = ros2_settings(ros2, profile)  # bad frame options: before any work
    if toa_correction is None:  # as run chose when it recorded the file
        toa_correction = recorded_toa_correction(path, fmt)
    # missing kernels: the interpreted ones run while a background process compiles them
    # (said at once, with progress), in this process only (workers would each compile)
    tiers = start_tiered(profile, association, max_targets, track, toa_correction, what="replay")
    pipeline = build_pipeline(profile, association, toa_correction)
    limits = InputLimits.for_profile(profile)
    jobs = usable_jobs(jobs, path, fmt, track, profile)
    if tiers is not None and tiers.is_interpreted and jobs > 1:
        click.echo(f"--jobs {jobs}: 1 while the kernels compile (interpreted)", err=True)
        jobs = 1
    files = frame_files(path) if jobs > 1 else None
    if max_targets:
        pipeline.set_max_targets(max_targets)
    failed = total = 0
    summary = ReplaySummary()
    stop = threading.Event()
    meta = {
        "command": "replay",
        "source": path,
        "profile": profile.name,
        **chosen_toa_correction(toa_correction),
    }
    sink = open_replay_output(
        output, force=force, record_profile=ros2["record_profile"], ros2=frame, metadata=meta
    )
    finalizers = Finalizers(exit_status=EXIT_PARTIAL)  # stuck on a blocked stdout: keep the
    if sink.owns_file:  # complete lines written so far; the replay is incomplete (1)
        finalizers.add(sink.close)
    if tiers is not None:  # a signal stops the background compile; a normal end leaves it
        finalizers.add(lambda: _say(tiers.close(stop_compile=stop.is_set())))
        finalizers.add(tiers.leave)  # the dispatchers back (a replay run in-process)
    try:
        with stop_on_signals(stop, finalizers):
            if files is not None:
                recipe = PipelineRecipe(
                    profile_name, calibration, association, toa_correction, max_targets
                )
                items = replay_files(
                    pipeline,
                    recipe,
                    files,
                    jobs,
                    background=background,
                    limits=limits,
                    track=track,
                    keep_frames=is_mcap_output(output),
                    stopped=stop.is_set,
                    on_workers=finalizers.add,  # a watchdog's exit stops them too
                )
            else:
                iq = profile.acquisition.signal == "iq"
                sources = iter_sources(path, fmt, background, limits, iq=iq)
                items = replay_tracked(pipeline, sources) if track else replay(pipeline, sources)
            with closing(items):
                for item in items:
                    sink.write(item)
                    summary.add(item)
                    if tiers is not None and tiers.is_interpreted:
                        tiers.between()  # the compiled kernels from the next acquisition on
                    total += 1
                    failed += item.error is not None
                    if stop.is_set():
                        break
            if stop.is_set():
                click.echo(f"stopped by a signal after {total} acquisitions", err=True)
                failed += 1
    except BaseException:
        sink.discard()
        if tiers is not None:  # (the finalizers do not run on this path)
            tiers.leave()
        raise
    if not finalizers.run_all():  # closes the file, unless the watchdog already did
        raise OutputError(f"--output {output}: could not be completed (see the log above)")
    if not sink.owns_file:
        sink.close()
    click.echo(summary.line(), err=True)
    if failed:
        click.echo(f"{failed} of {total} acquisitions could not be processed", err=True)
    return EXIT_PARTIAL if failed else EXIT_OK


def _say(line: str | None) -> None:
    if line:
        with contextlib.suppress(OSError):
            click.echo(line, err=True)
