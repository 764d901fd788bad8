"""``spiel-edge simulate --pty``: the virtual board on a pseudo-terminal."""

from __future__ import annotations

import threading

import click

from spiel_edge.cli import EXIT_OK
from spiel_edge.cli._signals import stop_on_signals
from spiel_edge.safety.shown import escape
from spiel_edge.sim.pty import serve_pty


@click.command("simulate")
@click.argument("url", default="sim://", required=False)
@click.option(
    "--pty",
    "use_pty",
    is_flag=True,
    help="Serve the board on a pseudo-terminal; its /dev/pts/N path is the first output line "
    "(and again on each replug).",
)
@click.option(
    "--link",
    type=click.Path(dir_okay=False),
    default=None,
    help="Keep this symlink pointing at the current pty, like a udev rule does.",
)
def command(url: str, use_pty: bool, link: str | None) -> int:
    """Run the virtual board described by URL (sim://[?scene=...&ber=...&unplug_after=...]).

    Connect with: spiel-edge run --port /dev/pts/N. Stops on SIGINT or SIGTERM.
    """
    if not use_pty:
        raise click.UsageError(
            "say how to serve the board: --pty (in-process use needs no server: --port sim://)"
        )
    if not url.lower().startswith("sim://"):
        raise click.UsageError(f"URL must start with sim://, got {url!r}")
    from spiel_edge.link.sim_options import modelled_envelope

    if modelled_envelope(url):  # over a pty the host cannot tell it from a real board
        click.echo(
            "this board's envelope is modelled: run the host with --toa-correction none "
            "(the learned correction is the real board's; docs/virtual-board.md)",
            err=True,
        )
    stop = threading.Event()
    with stop_on_signals(stop):
        device = serve_pty(url, link=link, stop=stop, announce=click.echo)
    stats, faults = device.board.stats, device.faults.stats
    click.echo(
        f"virtual board {escape(device.options.serial)}: {stats.acquisitions_sent} acquisitions sent, "
        f"{stats.overruns} overruns, {device.unplugs} unplugs, {faults.damaged_frames} frames damaged",
        err=True,
    )
    return EXIT_OK
