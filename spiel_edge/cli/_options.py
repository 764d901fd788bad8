"""Options shared by several commands."""

from __future__ import annotations

import click

from spiel_edge.profile.specs import MAX_TARGETS_LIMIT

PORT_ENV = "SPIEL_PORT"

port_option = click.option(
    "--port",
    envvar=PORT_ENV,
    default=None,
    metavar="URL",
    help="Board: /dev/ttyACM0, serial://PATH, usb://VID:PID[/SERIAL] or sim://[?options] "
    f"(env {PORT_ENV}). Default: the one board found by USB id.",
)


def board_port(port: str | None) -> str:
    """``--port`` as given, else the one attached board (DeviceError naming the choices)."""
    if port:
        return port
    from spiel_edge.link.discover import default_port  # USB scanning only when needed

    return default_port()


profile_option = click.option(
    "--profile",
    "profile_name",
    default="spiel-icra23",
    show_default=True,
    help="Built-in device profile name or a profile .toml path.",
)
calibration_option = click.option(
    "--calibration",
    type=click.Path(dir_okay=False),
    default=None,
    help="Calibration .toml (from `spiel-edge calibrate`) applied over the profile.",
)
association_option = click.option(
    "--association",
    type=click.Choice(["auto", "onnx", "geometric"]),
    default=None,
    help="Echo association (default: the profile's; auto = onnx when the model loads).",
)
max_targets_option = click.option(
    "--max-targets",
    type=click.IntRange(1, MAX_TARGETS_LIMIT),
    default=None,
    help="Report up to K targets per acquisition (default: the profile's [scene] max_targets).",
)
force_option = click.option(
    "--force",
    is_flag=True,
    help="Overwrite output files that already exist (never an input of the command).",
)

toa_correction_option = click.option(
    "--toa-correction",
    type=click.Choice(["auto", "onnx", "none"]),
    default=None,
    help="Learned ToA correction (default: the profile's, but none on the virtual board's echo "
    "model, and for an MCAP recording the one it was made with; auto/onnx = the model when it "
    "loads).",
)
jobs_option = click.option(
    "--jobs",
    "-j",
    type=click.IntRange(min=0, max=256),
    default=1,
    show_default=True,
    help="Worker processes over a spiel-csv folder's files (0: one per CPU; records as with 1).",
)
realtime_option = click.option(
    "--realtime",
    type=click.IntRange(1, 99),
    default=None,
    metavar="PRIORITY",
    help="Once the kernels are ready, stream in Linux's real-time class SCHED_FIFO at this "
    "priority (10 is plenty): low latency on a loaded computer (docs/robot.md). Needs the "
    "right (the systemd unit's LimitRTPRIO, or rtprio in limits.conf); without it a warning "
    "and normal scheduling.",
)
