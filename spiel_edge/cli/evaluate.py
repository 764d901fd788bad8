"""``spiel-edge evaluate``: accuracy on a labelled spiel-csv folder (optionally one split)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from spiel_edge.cli import EXIT_OK, EXIT_PARTIAL
from spiel_edge.cli._options import (
    association_option,
    calibration_option,
    jobs_option,
    max_targets_option,
    profile_option,
    toa_correction_option,
)
from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.errors import InputError
from spiel_edge.io.shown import escape
from spiel_edge.measure.evaluate import evaluate_folder, split_by_position
from spiel_edge.measure.scenes import evaluate_scenes
from spiel_edge.measure.track_eval import evaluate_tracked
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import resolve_profile
from spiel_edge.recordings.spiel_csv import frame_files
from spiel_edge.runtime.parallel import PipelineRecipe, resolve_jobs


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
@click.option("--json", "as_json", is_flag=True, help="Print the metrics as one JSON object.")
@click.option(
    "--track",
    is_flag=True,
    help="Also track each recording in time order and report the tracked error "
    "(`tracked`; docs/tracking.md).",
)
@jobs_option
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
    as_json,
    track,
    jobs,
) -> int:
    """Mean, median and p95 3-D error, fix rate and association accuracy on labelled recordings.

    FOLDER is a labelled spiel-csv folder, or a scene file (.npz from tools/train/build_scenes.py:
    several targets, or frames without background) for the per-number-of-targets metrics.
    """
    pipeline = build_pipeline(
        resolve_profile(profile_name, calibration), association, toa_correction
    )
    if max_targets:
        pipeline.set_max_targets(max_targets)
    if Path(folder).is_file():
        return _evaluate_scene_file(pipeline, folder, as_json)
    positions = None
    if split != "all":
        train, val = split_by_position([p.name for p in frame_files(folder)], val_fraction)
        positions = train if split == "train" else val
    skip = exclude_z or EXCLUDED_Z_MM
    recipe = PipelineRecipe(profile_name, calibration, association, toa_correction, max_targets)
    ev = evaluate_folder(
        pipeline,
        folder,
        background,
        positions=positions,
        exclude_z=skip,
        jobs=resolve_jobs(jobs),
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
    if as_json:
        click.echo(json.dumps(summary))
    else:
        _print_table(summary)
        print_scene_table(summary["by_targets"])
    for message in ev.failed:
        click.echo(f"failed: {escape(message)}", err=True)
    if not sum(ev.frames.values()):  # nothing was evaluated: an error, not a result
        raise InputError(f"{folder}: no usable labelled acquisitions ({len(ev.failed)} failed)")
    return EXIT_PARTIAL if ev.failed else EXIT_OK


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
