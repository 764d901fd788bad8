"""``spiel-edge warmup``: compile every pipeline kernel into numba's cache before a start."""

from __future__ import annotations

import json

import click

from spiel_edge.cli import EXIT_OK


@click.command("warmup")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def command(as_json: bool) -> int:
    """Compile (or load) every kernel into the cache this environment uses (NUMBA_CACHE_DIR
    when set: run it with the service's environment, as `service install` does)."""
    from spiel_edge.runtime.warmup import warmup

    result = warmup()
    if as_json:
        click.echo(json.dumps(result))
        return EXIT_OK
    click.echo(
        f"{result['kernels']} kernels in {result['seconds']:.1f} s: "
        f"{len(result['compiled'])} compiled, {len(result['cache_hits'])} loaded from the cache "
        f"({result['cache_dir']})"
    )
    return EXIT_OK
