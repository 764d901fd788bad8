"""``spiel-edge background``: capture the empty scene for background subtraction on hardware."""

from __future__ import annotations

import sys
import threading

import click

from spiel_edge.cli._options import board_port, force_option, port_option
from spiel_edge.cli._signals import stop_on_signals
from spiel_edge.device import DeviceSession
from spiel_edge.runtime.background_capture import median_background, save_background
from spiel_edge.safety.guard import FilePlan
from spiel_edge.safety.shown import escape


@click.command("background")
@port_option
@click.option(
    "--frames",
    "count",
    type=click.IntRange(min=1),
    default=32,
    show_default=True,
    help="Acquisitions to take; the per-sample median is kept.",
)
@click.option(
    "--rate",
    type=click.FloatRange(0, 10000),
    default=50.0,
    show_default=True,
    help="Acquisitions per second asked of the board while capturing.",
)
@click.option(
    "--samples",
    "n_samples",
    type=click.IntRange(0, 4096),
    default=0,
    help="Samples per channel to ask for (0: the board's default).",
)
@click.option(
    "--output",
    "-o",
    required=True,
    type=click.Path(dir_okay=False),
    help="Where to save it: FILE.npy, or a spiel-csv frames file for any other suffix.",
)
@force_option
def command(port, count, rate, n_samples, output, force) -> int:
    """Capture the scene without the target; use it with `run --background FILE`."""
    FilePlan(force).output(output, "--output")  # before the capture, not after
    port = board_port(port)
    stop = threading.Event()
    # no reconnect: a board that goes away ends the capture with an error, never a silent wait
    with stop_on_signals(stop), DeviceSession(port, reconnect=False) as session:
        session.start_stream(rate_hz=rate, n_samples=n_samples)
        with click.progressbar(length=count, label="capturing background", file=sys.stderr) as bar:

            def counted():
                for acq in session.acquisitions(stop):
                    bar.update(1)
                    yield acq

            background = median_background(counted(), count, stop)
        session.stop_stream()
    path = save_background(output, background)
    click.echo(
        f"{escape(path)}: background of {count} acquisitions, shape {background.shape}", err=True
    )
    return 0
