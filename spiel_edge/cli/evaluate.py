"""``spiel-edge evaluate``: accuracy on a labelled spiel-csv folder (optionally one split)."""

from __future__ import annotations

import json
from dataclasses import dataclass
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
from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.errors import ConfigError, InputError
from spiel_edge.measure.evaluate import evaluate_folder, evaluate_labelled, split_by_position
from spiel_edge.measure.scenes import evaluate_scenes
from spiel_edge.measure.track_eval import evaluate_tracked
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import resolve_profile
from spiel_edge.recordings.kinds import recording_kind
from spiel_edge.recordings.labelled import load_labelled
from spiel_edge.recordings.spiel_csv import frame_files
from spiel_edge.runtime.parallel import PipelineRecipe, resolve_jobs
from spiel_edge.runtime.tiered import tiered_work
from spiel_edge.safety.guard import FilePlan
from spiel_edge.safety.limits import InputLimits
from spiel_edge.safety.shown import escape
from spiel_edge.view import require_matplotlib


@click.command("evaluate")
@click.argument("folder", type=click.Path(exists=True))
@click.option(
    "--background",
    type=click.Path(exists=True, file_okay=False),
    default=None,
    help="Folder of same-named target-free frames.",
)
@profile_option
@calibration_option
@association_option
@max_targets_option
@toa_correction_option
@click.option(
    "--split",
    type=click.Choice(["all", "train", "val"]),
    default="all",
    show_default=True,
    help="Evaluate on every position, or one side of the split by (x, y) position.",
)
@click.option(
    "--val-fraction",
    type=click.FloatRange(0.0, 1.0, min_open=True, max_open=True),
    default=0.3,
    show_default=True,
    help="Share of (x, y) positions in the validation split.",
)
@click.option(
    "--exclude-z",
    multiple=True,
    type=float,
    help="Leave out a height (mm); repeatable (default: the mislabelled z = 90 mm).",
)
@click.option(
    "--max-z",
    type=float,
    default=180.0,
    show_default=True,
    help="Headline metrics over heights <= this.",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["spiel-csv", "stof-chirp"]),
    default=None,
    help="Recording format (default: stof-chirp for a folder of SToF-Chirp sequences, else "
    "spiel-csv). stof-chirp: range metrics of a one-transducer board (docs/hardware-ranging.md).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the metrics as one JSON object.")
@click.option(
    "--track",
    is_flag=True,
    help="Also track each recording in time order and report the tracked error "
    "(`tracked`; docs/tracking.md).",
)
@jobs_option
@click.option(
    "--plot",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also draw the error by position as a PNG (needs the 'plot' extra).",
)
@force_option
def command(
    folder,
    background,
    profile_name,
    calibration,
    association,
    max_targets,
    toa_correction,
    split,
    val_fraction,
    exclude_z,
    max_z,
    fmt,
    as_json,
    track,
    jobs,
    plot,
    force,
) -> int:
    """Mean, median and p95 3-D error, fix rate and association accuracy on labelled recordings.

    FOLDER is a labelled spiel-csv folder, a labelled .npz (the vendored
    spiel_edge/data/spiel_icra23_subset.npz: frames, backgrounds, truth_mm, names), or a scene
    file (.npz from tools/train/build_scenes.py: several targets, or frames without background)
    for the per-number-of-targets metrics; told by its content.
    """
    if plot:  # before any work
        require_matplotlib("--plot")
        FilePlan(force).output(plot, "--plot")
    if fmt == "stof-chirp" or (fmt is None and _is_stof(folder)):
        return _evaluate_ranging(folder, profile_name, calibration, as_json)
    profile = resolve_profile(profile_name, calibration)
    # missing kernels: the interpreted ones run while a background process compiles them;
    # the compiled ones from a kernel call once loaded (docs/first-start.md)
    with tiered_work(profile, association, max_targets, track, toa_correction, "evaluate") as t:
        if t is not None and t.is_interpreted and jobs != 1:
            click.echo(f"--jobs {jobs}: 1 while the kernels compile (interpreted)", err=True)
            jobs = 1
        return _evaluate(
            profile,
            EvaluateOptions(
                folder=folder,
                background=background,
                profile_name=profile_name,
                calibration=calibration,
                association=association,
                max_targets=max_targets,
                toa_correction=toa_correction,
                split=split,
                val_fraction=val_fraction,
                exclude_z=exclude_z,
                max_z=max_z,
                as_json=as_json,
                track=track,
                jobs=jobs,
                plot=plot,
            ),
        )


@dataclass(frozen=True)
class EvaluateOptions:
    """`evaluate`'s options, as given (the profile is resolved apart)."""

    folder: str
    background: str | None
    profile_name: str
    calibration: str | None
    association: str | None
    max_targets: int | None
    toa_correction: str | None
    split: str
    val_fraction: float
    exclude_z: tuple
    max_z: float | None
    as_json: bool
    track: bool
    jobs: int | None
    plot: str | None


def _evaluate(profile, o: EvaluateOptions) -> int:
    folder, background, split, track, max_z = o.folder, o.background, o.split, o.track, o.max_z
    association, max_targets, toa_correction = o.association, o.max_targets, o.toa_correction
    pipeline = build_pipeline(profile, association, toa_correction)
    if max_targets:
        pipeline.set_max_targets(max_targets)
    kind = recording_kind(folder, ("spiel-csv", "labelled", "scenes"))
    if background and kind != "spiel-csv":
        raise ConfigError(f"--background is for a spiel-csv folder; {folder} is {kind}")
    if kind == "scenes":
        return _evaluate_scene_file(pipeline, folder, o.as_json)
    if kind == "labelled" and track:
        raise ConfigError("--track needs a spiel-csv folder (recordings in time order)")
    positions = None
    skip = o.exclude_z or EXCLUDED_Z_MM
    if kind == "labelled":
        data = load_labelled(folder, InputLimits.for_profile(pipeline.profile), exclude_z=skip)
        if split != "all":
            train, val = split_by_position(data.names, o.val_fraction)
            data = load_labelled(
                folder,
                InputLimits.for_profile(pipeline.profile),
                positions=train if split == "train" else val,
                exclude_z=skip,
            )
        ev = evaluate_labelled(pipeline, data)
    else:
        if split != "all":
            train, val = split_by_position([p.name for p in frame_files(folder)], o.val_fraction)
            positions = train if split == "train" else val
        recipe = PipelineRecipe(
            o.profile_name, o.calibration, association, toa_correction, max_targets
        )
        ev = evaluate_folder(
            pipeline,
            folder,
            background,
            positions=positions,
            exclude_z=skip,
            jobs=resolve_jobs(o.jobs),
            recipe=recipe,
        )
    summary = {
        "split": split,
        "max_z": max_z,
        "association": pipeline.associator.name,
        **ev.summary(max_z=max_z),
    }
    if track:
        summary["tracked"] = evaluate_tracked(
            pipeline, folder, background, positions=positions, exclude_z=skip, max_z=max_z
        )
    if o.as_json:
        click.echo(json.dumps(summary))
    else:
        _print_table(summary)
        print_scene_table(summary["by_targets"])
        click.echo(COLUMNS)
    if o.plot and ev.by_position:
        from spiel_edge.view.evaluation import draw_error_by_position

        draw_error_by_position(ev.by_position, o.plot)
        click.echo(f"plot written to {o.plot}", err=True)
    for message in ev.failed:
        click.echo(f"failed: {escape(message)}", err=True)
    if not sum(ev.frames.values()):  # nothing was evaluated: an error, not a result
        raise InputError(f"{folder}: no usable labelled acquisitions ({len(ev.failed)} failed)")
    return EXIT_PARTIAL if ev.failed else EXIT_OK


def _is_stof(folder) -> bool:
    from spiel_edge.recordings.stof_chirp import sequence_folders

    if not Path(folder).is_dir() or any(Path(folder).glob("*_frames.csv")):
        return False
    try:
        return bool(sequence_folders(folder))
    except InputError:
        return False


def _evaluate_ranging(folder, profile_name, calibration, as_json) -> int:
    """Range metrics over the labelled SToF-Chirp sequences in ``folder``."""
    from spiel_edge.cli._recording_profile import recording_profile
    from spiel_edge.measure.ranging_eval import range_errors, summarize

    profile = recording_profile(folder, "stof-chirp", profile_name, calibration)
    summary = {"profile": profile.name, **summarize(range_errors(build_pipeline(profile), folder))}
    if not summary["frames"]:
        raise InputError(f"{folder}: no labelled SToF-Chirp frames (truth table beside the specs)")
    if as_json:
        click.echo(json.dumps(summary))
        return EXIT_OK
    click.echo(f"{'distance':>9} {'frames':>7} {'mean':>8} {'std':>7} {'MAE':>7}")
    for d, s in summary.get("by_distance", {}).items():
        click.echo(
            f"{d:>9} {s['frames']:>7} {s['mean_mm']:>8.3f} {s['std_mm']:>7.3f} {s['mae_mm']:>7.3f}"
        )
    click.echo(
        f"frames {summary['frames']}, with a range {summary['with_range']:.1%}, MAE "
        f"{fmt(summary.get('mae_mm'), '.3f')} mm, rms of per-distance std "
        f"{fmt(summary.get('rms_std_mm'), '.3f')} mm, > 1 mm off "
        f"{fmt(summary.get('over_1mm'), '.2%')}, 95 % coverage {fmt(summary.get('coverage95'), '.1%')}"
    )
    return EXIT_OK


SCENE_COLUMNS = (
    "targets: true targets per acquisition; recall: true targets found within 30 mm; all: "
    "acquisitions with every one found; prec: reported targets that are true; mean: their "
    "error (mm); per fr: targets reported per acquisition; cover: true position inside the "
    "reported 95 % ellipsoid; cov1: the same for the best target of one-target acquisitions"
)
COLUMNS = (
    "fix: acquisitions with a position; mean/median/p95: 3-D error (mm) against the label; "
    "association accuracy: matched echo = the echo nearest the true echo time, per channel\n"
    + SCENE_COLUMNS
)


def fmt(v, spec=".1f"):
    return "-" if v is None else format(v, spec)


def _evaluate_scene_file(pipeline, path: str, as_json: bool) -> int:
    tally = evaluate_scenes(pipeline, path)
    summary = {
        "scenes": str(path),
        "association": pipeline.associator.name,
        "max_targets": pipeline.max_targets,
        "by_targets": tally.summary(),
    }
    if as_json:
        click.echo(json.dumps(summary))
    else:
        print_scene_table(summary["by_targets"])
        click.echo(SCENE_COLUMNS)
    return EXIT_OK


def print_scene_table(by_targets: dict) -> None:
    click.echo(
        f"{'targets':>7} {'frames':>7} {'recall':>7} {'all':>6} {'prec':>6} {'mean':>6} "
        f"{'per fr':>6} {'cover':>6} {'cov1':>6}"
    )
    for n, s in by_targets.items():

        def fmt(v, spec=".1%"):
            return "-" if v is None else format(v, spec)

        click.echo(
            f"{n:>7} {s['frames']:>7} {fmt(s['recall']):>7} {fmt(s['all_found']):>6} "
            f"{fmt(s['precision']):>6} {fmt(s['mean_mm'], '.1f'):>6} "
            f"{fmt(s['targets_per_frame'], '.2f'):>6} {fmt(s['coverage']):>6} "
            f"{fmt(s['coverage_best']):>6}"
        )


def _print_table(summary: dict) -> None:
    click.echo(f"{'z (mm)':>8} {'frames':>7} {'fix':>6} {'mean':>7} {'median':>7} {'p95':>7}")
    rows = [(z, s) for z, s in summary["by_height"].items()] + [
        (f"<={summary['max_z']:g}", summary)
    ]
    for name, s in rows:
        click.echo(
            f"{name:>8} {s['frames']:>7} {fmt(s['fix_rate'], '.0%'):>6} {fmt(s['mean_mm']):>7} "
            f"{fmt(s['median_mm']):>7} {fmt(s['p95_mm']):>7}"
        )
    click.echo(
        f"association accuracy {fmt(summary['association_accuracy'], '.1%')}, "
        f"F1 {fmt(summary['association_f1'], '.3f')} ({summary['association']})"
    )
    tracked = summary.get("tracked")
    if tracked and tracked["fixes"]:
        click.echo(
            f"tracked: mean {tracked['tracked_mean_mm']:.1f} mm vs per acquisition "
            f"{tracked['per_acquisition_mean_mm']:.1f} mm over {tracked['fixes']} fixes "
            f"({tracked['on_track_share']:.0%} on a confirmed track); the static target's "
            f"track {tracked['static_track_mean_mm']:.1f} mm"
        )
