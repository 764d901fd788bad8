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
@click.option("--association", type=click.Choice(["auto", "onnx", "geometric"]), default=None)
@click.option("--no-startup", is_flag=True, help="Skip the fresh-interpreter start-up timing.")
def command(as_json: bool, repeat: int, association: str | None, no_startup: bool) -> int:
    """Median and p95 microseconds per acquisition, real 4x64 and synthetic 8x256 / 16x1024."""
    result = run_bench(repeat=repeat, association=association, startup=not no_startup)
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
    if result.get("onnx_scoring"):
        click.echo(
            f"onnx scoring: median {result['onnx_scoring']['scoring_us']['median']:.1f} us per acquisition"
        )
    if "startup_s" in result:
        click.echo(
            f"start-up (fresh interpreter, import + first acquisition): {result['startup_s']} s"
        )
    if as_json:
        click.echo(to_json(result))
    return 0
