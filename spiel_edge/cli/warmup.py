"""``spiel-edge warmup``: compile every pipeline kernel into numba's cache before a start."""

from __future__ import annotations

import json
import sys

import click

from spiel_edge.cli import EXIT_OK


@click.command("warmup")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option(
    "--isolate/--in-process",
    default=True,
    show_default=True,
    help="Each group of kernels in a child process of its own (bounded peak memory).",
)
def command(as_json: bool, isolate: bool) -> int:
    """Compile (or load) every kernel into the cache this environment uses (NUMBA_CACHE_DIR
    when set: run it with the service's environment, as `service install` does). Progress
    goes to stderr: a bar on a terminal, one line per kernel compiled elsewhere."""
    from spiel_edge.runtime.compile_progress import Progress
    from spiel_edge.runtime.warmup import STEPS, warmup

    progress = Progress(total=1)
    progress.say(
        f"spiel-edge warmup: loading or compiling every kernel in {len(STEPS)} steps "
        "(compiling them all takes minutes; loading them seconds)"
    )
    status = _status()
    if status is not None:
        progress.total = max(len(status["missing"]), 1)
        progress.say(
            f"{len(status['missing'])} of {status['total']} kernels have no compiled copy for "
            "this CPU (a few helpers only ever compile into others); cache: "
            f"{status['cache_dir'] or 'no writable folder'}"
        )
    result = warmup(isolate=isolate, progress=progress)
    progress.finish()
    if as_json:
        click.echo(json.dumps(result))
        return EXIT_OK
    click.echo(
        f"{result['kernels']} kernels in {result['seconds']:.1f} s: "
        f"{len(result['compiled'])} compiled, {len(result['cache_hits'])} loaded from the cache "
        f"({result['cache_dir']})"
    )
    return EXIT_OK


def _status() -> dict | None:
    from spiel_edge.runtime.first_start import kernel_status

    try:
        return kernel_status()
    except Exception as exc:  # the count is a courtesy: the warm-up itself will tell
        print(f"spiel-edge warmup: kernel count unavailable ({exc})", file=sys.stderr)
        return None
