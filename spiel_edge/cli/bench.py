"""``spiel-edge bench``: speed per stage and end to end; JSON as the last line with --json."""

from __future__ import annotations

import click

from spiel_edge.measure.bench import run_bench, to_json


@click.command("bench")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object as the last line.")
@click.option(
    "--repeat",
    type=click.IntRange(1, 1000),
    default=5,
    show_default=True,
    help="Passes over the acquisitions.",
)
@click.option(
    "--association",
    type=click.Choice(["auto", "onnx", "geometric"]),
    default=None,
    help="Echo association to time (default: the profile's).",
)
@click.option(
    "--no-startup",
    is_flag=True,
    help="Skip the fresh-interpreter start-up timing and the peak-memory run.",
)
@click.option(
    "--reference",
    "reference_count",
    default=8,
    show_default=True,
    help="Acquisitions for the numpy/scipy reference (0: skip it).",
)
@click.option(
    "--run-path/--no-run-path",
    default=True,
    show_default=True,
    help="CPU per record of the whole `run` over a pty from `simulate --pty` (two runs).",
)
@click.option(
    "--first-start",
    is_flag=True,
    help="Also the first-start figures on an empty cache (compiles every kernel: minutes).",
)
def command(
    as_json: bool,
    repeat: int,
    association: str | None,
    no_startup: bool,
    reference_count: int,
    run_path: bool,
    first_start: bool,
) -> int:
    """Median and p95 microseconds per acquisition, real 4x64 and synthetic 8x256 / 16x1024:
    per stage (staged path), fused vs staged end to end, and the numpy/scipy reference."""
    result = run_bench(
        repeat=repeat,
        association=association,
        startup=not no_startup,
        reference_count=reference_count,
    )
    for name in ("real_4x64", "synthetic_8x256", "synthetic_16x1024"):
        e2e = result[name]["end_to_end"]
        stages = ", ".join(
            f"{s} {v['median_us']:.0f}"
            for s, v in result[name].items()
            if isinstance(v, dict) and s != "end_to_end"
        )
        click.echo(
            f"{name}: end to end median {e2e['median_us']:.0f} us, p95 {e2e['p95_us']:.0f} us ({stages})"
        )
    for name in ("paths_4x64", "paths_8x256", "paths_16x1024"):
        f, s = result[name]["fused"], result[name]["staged"]
        click.echo(
            f"{name}: fused median {f['median_us']:.0f} us (p95 {f['p95_us']:.0f}), staged "
            f"median {s['median_us']:.0f} us (p95 {s['p95_us']:.0f}): staged / fused "
            f"{result[name]['staged_over_fused']:.2f}"
        )
    ref = result.get("reference_4x64")
    if ref is not None and ref["available"]:
        click.echo(
            f"numpy/scipy reference 4x64: median {ref['median_ms']:.1f} ms over "
            f"{ref['acquisitions']} acquisitions: {ref['reference_over_fused']:.0f}x the fused path"
        )
    elif ref is not None:
        click.echo(f"numpy/scipy reference: not run ({ref['why']})")
    if result.get("onnx_scoring"):
        click.echo(
            f"onnx scoring: median {result['onnx_scoring']['scoring_us']['median']:.1f} us per acquisition"
        )
    scene = result.get("scene_4_tracked")
    if scene:
        click.echo(
            f"fused, {scene['k']} targets, no background, tracked: median {scene['median_us']:.0f} us, "
            f"p95 {scene['p95_us']:.0f} us per acquisition"
        )
    tracker = result.get("tracker_8_tracks")
    if tracker:
        click.echo(
            f"tracker ({tracker['tracks_median']} tracks): median {tracker['median_us']:.1f} us, "
            f"p95 {tracker['p95_us']:.1f} us per acquisition"
        )
    if "startup_s" in result:
        click.echo(
            f"start-up (fresh interpreter, import + first acquisition): {result['startup_s']} s"
        )
    if "peak_rss_mib" in result:
        click.echo(f"peak RSS of run --port sim:// --frames 300: {result['peak_rss_mib']} MiB")
    if run_path:
        from spiel_edge.measure.bench_run import run_path_cpu

        result["run_path_4x64"] = run = run_path_cpu()
        scene = result.get("scene_4_tracked")
        if scene:
            run["over_pipeline"] = round(run["cpu_us_per_record"] / scene["median_us"], 2)
        click.echo(
            f"run over a pty (4x64, 4 targets, tracked, NDJSON): {run['cpu_us_per_record']:.0f} "
            f"CPU-us per record ({run.get('over_pipeline', '-')}x the pipeline's), "
            f"latency at --rate 0 {run['latency_ms']}"
        )
        # the board's default pace (issue 39): the same path, idle between acquisitions
        result["run_path_4x64_50hz"] = paced = run_path_cpu(500, 50.0)
        click.echo(
            f"the same at the board's 50/s: {paced['cpu_us_per_record']:.0f} CPU-us per record, "
            f"{paced['wakeups_per_record']} wake-ups per record"
        )
    if not no_startup:  # a tiered start (docs/first-start.md): cheap, the compile is stopped
        from spiel_edge.measure.bench_run import first_record_cold, interpreted_tier

        result["tiered_start"] = tiered = {
            "cold_run_5_frames": first_record_cold(),
            "interpreted_4x64": interpreted_tier(),
        }
        cold, tier = tiered["cold_run_5_frames"], tiered["interpreted_4x64"]
        click.echo(
            f"first record from an empty cache (run --port sim:// --frames 5): "
            f"{cold['first_record_s']} s; interpreted kernels: median "
            f"{tier['interpreted_median_us'] / 1e3:.1f} ms per acquisition "
            f"(compiled {tier['compiled_median_us']:.0f} us)"
        )
    if first_start:
        from spiel_edge.measure.bench_run import cold_figures

        result["first_start"] = cold_figures()
        click.echo(f"first start (empty cache): {result['first_start']}")
    if as_json:
        click.echo(to_json(result))
    return 0
